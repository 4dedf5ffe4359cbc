"""``pipeline track shape`` / ``track pose``: a soft arm's shape, or a manipulator's camera-to-root pose, in every
frame of a video or an image sequence (``pipeline.track``).

Frames come from ``--video FILE`` (decoded one by one, never all in memory) or ``--frames 'GLOB'`` (sorted by
name); masks from the segmenter options (``--segmenter file --mask-pattern 'masks/{frame:05d}.png'`` reads a mask
per frame, numbered as the video's frames). ``--out TRAJ.jsonl`` gets one line per frame as soon as it is done
(flushed, so a stopped run keeps every finished frame) and a summary line last.
"""

from __future__ import annotations

import argparse
import math

from pipeline.cli._args import add_rim_offset_argument
from pipeline.cli._segmenter_args import add_segmenter_arguments
from pipeline.cli.shape import add_model_arguments

#: ``track pose --smooth-window``'s default: 1, none. On tuning videos it helps noisy masks and hurts a learned
#: segmenter's under a hand-held camera (docs/tracking.md): an option.
SMOOTH_WINDOW = 1


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "track",
        help="video tracking: soft-arm shape or manipulator pose per frame, warm-started from the previous frame",
        description="Track a robot through a video or an image sequence, one estimate per frame.",
    )
    kinds = parser.add_subparsers(dest="track_kind", metavar="<kind>", title="kinds", required=True)
    shape = kinds.add_parser(
        "shape",
        help="soft continuum arm: centreline and radii per frame",
        description="Fit the soft arm in the first frame from scratch, then every frame from the previous "
        "estimate (one start, few iterations); a frame whose loss jumps above --reinit-ratio times the running "
        "loss (or, with --drift-ratio, whose running loss has climbed that many times its lowest) is fitted from "
        "scratch again (keeping the base end of the last estimate). Frames that cannot be read "
        "or show no robot are reported as skipped. The segmenter keeps every mask component: where there are "
        "several large ones, a full fit takes the one a tube of the arm's size explains best, a warm frame the one "
        "the last estimate covers. Results refer to the undistorted image.",
    )
    _add_source_arguments(shape, live=True)
    shape.add_argument("--length", required=True, type=float, metavar="M", help="arm length, metres")
    shape.add_argument("--base-radius", required=True, type=float, metavar="M", help="radius at the base, metres")
    shape.add_argument("--tip-radius", required=True, type=float, metavar="M", help="radius at the tip, metres")
    shape.add_argument(
        "--order", default="auto", metavar="N|auto",
        help="Bezier order of the first (and any re-initialised) frame's fit, or auto (default: orders 2 to 5, the "
        "best kept); later frames keep the order of the estimate they start from",
    )  # fmt: skip
    add_model_arguments(shape)
    shape.add_argument("--warm-pcc-iterations", type=int, default=None, metavar="N",
                       help="pcc: rendered steps refining a warm frame's sections, from its Bezier fit's and the last "
                       "frame's (default 30; after a full fit 150)")
    shape.add_argument(
        "--keypoint-mode", choices=("mask", "endpoint", "keypoints"), default="keypoints",
        help="loss: mask only, mask + the tip, or mask + --keypoints points along the arm (default keypoints)",
    )  # fmt: skip
    shape.add_argument("--keypoints", type=int, default=4, metavar="K", help="keypoints along the arm (default 4)")
    shape.add_argument(
        "--base-pixel", metavar="U,V",
        help="pixel of the arm's base for full fits (default: the skeleton end nearer the image border)",
    )  # fmt: skip
    shape.add_argument("--iterations", type=int, default=200, metavar="N",
                       help="Adam iterations of a full fit (first frame, re-initialisations; default 200)")
    shape.add_argument("--starts", type=int, default=8, metavar="N", help="hypotheses of a full fit (default 8)")
    shape.add_argument("--seed", type=int, default=0, metavar="N", help="seed of the random starts (default 0)")
    shape.add_argument("--max-side", type=int, default=480, metavar="PX",
                       help="working resolution (longest side of the cropped mask) of the full and the warm fits "
                       "(default 480; on frames larger than 640x360, 320 is about 15 %% faster a warm frame and "
                       "less accurate)")
    add_rim_offset_argument(shape, auto="searched over the first frames' masks together (--rim-search-frames) and "
                            "held; those frames are written once it is found",
                            image="read from each of the first frames' colour edges across the mask's outline "
                            "(--rim-search-frames), the median so far held (off by default: compressed video frames "
                            "misread it, docs/tracking.md)")
    shape.add_argument("--rim-search-frames", type=int, default=8, metavar="N",
                       help="with --rim-offset-px auto: the fitted frames it is searched over; with image: the frames "
                       "it is read on (default 8)")
    shape.add_argument("--warm-iterations", type=int, default=30, metavar="N",
                       help="Adam iterations of a warm-started frame (default 30)")
    shape.add_argument("--warm-prefit-iterations", type=int, default=None, metavar="N",
                       help="pre-fit steps (no rendering) of a warm-started frame (default: at most 6 "
                       "Levenberg-Marquardt steps; 100 with --warm-prefit-solver adam)")
    shape.add_argument("--warm-prefit-solver", choices=("lm", "adam"), default="lm",
                       help="the warm frames' pre-fit: Levenberg-Marquardt (default, within a few steps) or "
                       "Adam (the pre-fit before 2026-11-27, 100 steps; about 0.4 s more per frame)")
    shape.add_argument(
        "--warm-hypotheses", default="1", metavar="I,...|none",
        help="mask hypotheses that start beside the last estimate in each warm fit (0: per-point depths from the "
        "widths, 1: their straight line, 2: the opposite slope, 3: constant depth, 4 and 5: 0 and 1 with the taper "
        "at 3D arc length; default 1; 0,1,4,5: nearer on S-shaped arms for 1.35-1.65x a warm frame's time, "
        "docs/tracking.md; none: the last estimate alone)",
    )  # fmt: skip
    shape.add_argument("--warm-keep-start", action=argparse.BooleanOptionalAction, default=True,
                       help="each warm fit also starts from the last estimate as it is, not pre-fitted, beside its "
                       "pre-fitted self and the hypotheses (default on)")
    shape.add_argument("--carry-moments", action="store_true",
                       help="each warm fit's Adam begins with the state the last frame's fit ended with, not zeros "
                       "(nearer in 2D on single-bend and S-shaped tuning videos, farther on two-section ones: "
                       "docs/tracking.md; default off)")
    shape.add_argument("--warm-slow-start", type=float, default=None, metavar="F",
                       help="each warm fit also starts its pre-fitted last estimate a second time at F times the "
                       "rate (default 0: not; 0.2 was nearer in 3D on Bezier tuning videos, farther on two-section "
                       "ones: docs/tracking.md)")
    shape.add_argument("--reinit-ratio", type=float, default=3.0, metavar="R",
                       help="fit a frame from scratch when its loss exceeds R times the running loss (default 3)")
    _add_drift_ratio(shape, "none", ": a soft arm's loss changes with its shape, up to 3.8x over a bend on tuning videos")
    shape.add_argument("--fixed-base", action="store_true",
                       help="hold the base point and direction found on the first tracked frame (the arm's base does "
                       "not move relative to the camera)")
    shape.add_argument("--compile", action="store_true",
                       help="warm fits through torch.compile (needs a C++ compiler), on the tensor path: on CPU slower "
                       "than the default since its losses run as compiled numba kernels (0.20 against 0.13 s per warm "
                       "frame), after seconds to tens of seconds of compiling; not measured on CUDA (docs/tracking.md)")
    shape.add_argument("--predict", action="store_true",
                       help="start each warm fit from a constant-velocity prediction of the last two estimates "
                       "(docs/tracking.md: a faster, less accurate recipe with it)")
    shape.add_argument("--batch-frames", type=int, default=None, metavar="N",
                       help="fit N warm frames together in one batch, all started from the estimate before them "
                       "(recorded videos: 2-3x the frames per second, 11-12 at 640x360 with 8 on two cores; lines "
                       "written per batch; default 1, each frame as it comes; not with --compile; docs/tracking.md). "
                       "With --live: the most frames one fit takes (default 8)")
    _add_output_arguments(shape)
    add_segmenter_arguments(shape, default="auto")
    shape.set_defaults(func=run_shape)
    _add_pose_parser(kinds)


def _add_source_arguments(parser: argparse.ArgumentParser, *, live: bool = False) -> None:
    parser.add_argument("--camera", required=True, metavar="CAM.json", help="camera intrinsics file")
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--video", metavar="FILE", help="video file (anything OpenCV's VideoCapture reads)")
    source.add_argument("--frames", metavar="GLOB", help="image files, e.g. 'frames/*.png' (sorted by name)")
    if live:
        source.add_argument(
            "--device", type=int, metavar="N",
            help="a live camera, OpenCV's camera N (0: the first; calibrated as --camera says), read as --live; "
            "time_s is the seconds since its first frame; the run ends at --stop or Ctrl-C (the summary is written)",
        )  # fmt: skip
        parser.add_argument(
            "--live", action="store_true",
            help="read (and segment) the frames in a background thread while the tracker fits, each fit taking the "
            "frames that arrived meanwhile, at most --batch-frames (default 8 then): one at a time while it keeps up "
            "(implied by --device; docs/tracking.md)",
        )  # fmt: skip
        parser.add_argument(
            "--drop-late", action="store_true",
            help="with --live: when --batch-frames frames wait, drop the oldest for the newest (a line with "
            "\"skipped\": \"dropped ...\"), so the results stay within about a batch of the camera",
        )  # fmt: skip
    parser.add_argument("--start", type=int, default=0, metavar="N", help="first frame (default 0)")
    parser.add_argument("--stop", type=int, metavar="N", help="stop before this frame (default: the last)")
    parser.add_argument("--step", type=int, default=1, metavar="N", help="take every N-th frame (default 1)")
    parser.add_argument(
        "--fps", type=float, metavar="F",
        help="frame rate for time_s (default: the video's; none for --frames, time_s is then null)",
    )  # fmt: skip


def _add_output_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", metavar="TRAJ.jsonl", help="write one JSON line per frame and a summary line")
    parser.add_argument("--overlay-video", metavar="OUT.mp4", help="write the frames with the fitted outline")
    parser.add_argument("--quiet", action="store_true",
                        help="no progress bar (there is none when stderr is not a terminal)")


def _add_pose_parser(kinds: argparse._SubParsersAction) -> None:
    from pipeline.cli.pose import add_fit_arguments, add_joint_arguments, add_robot_arguments

    pose = kinds.add_parser(
        "pose",
        help="manipulator: camera-to-root pose T_cam_root per frame",
        description="Fit the manipulator's T_cam_root in the first frame from scratch (the options of pipeline pose), "
        "then every frame from the previous pose (one start, --warm-iterations at --warm-max-side); a frame whose "
        "loss jumps above --reinit-ratio times the running loss, or whose running loss has climbed --drift-ratio "
        "times its lowest, is fitted from scratch again. Joint readings per "
        "frame come from --joints-csv (or one set for all frames from --joints / --joints-file). With "
        "--static-camera, one T_cam_root is also refined over all frames together (summary line). Frames that "
        "cannot be read or show no robot are reported as skipped. Results refer to the undistorted image.",
    )
    _add_source_arguments(pose)
    add_robot_arguments(pose)
    add_joint_arguments(pose, csv=True)
    add_fit_arguments(pose)
    pose.add_argument("--warm-iterations", type=int, default=15, metavar="N",
                      help="Adam iterations of a warm-started frame, before its polish (default 15)")
    pose.add_argument("--warm-max-side", type=int, default=480, metavar="PX",
                      help="working resolution of a warm-started frame (longest side, default 480; 320 takes "
                      "15-40 %% less time a frame and is less accurate on a segmenter's masks)")
    pose.add_argument("--warm-newton-steps", type=int, default=5, metavar="N",
                      help="Gauss-Newton polish steps of a warm-started frame (default 5)")
    pose.add_argument("--warm-boundary-offset", choices=("auto", "always", "never"), default="never",
                      help="where links are drawn as hulls of their visual meshes: fit how far the mask's outline "
                      "lies outside the robot's (a segmenter's dilation or erosion) in a warm-started frame's "
                      "polish, beside the pose: auto when the visual meshes' loss at the answer before the polish "
                      "is above --warm-outline-loss (nearer on some noisy videos for 1.2-1.5x the time, farther on a "
                      "learned segmenter's), always, or never (default); with --primitive cad it is always fitted")
    pose.add_argument("--warm-outline-polish", nargs="?", choices=("auto", "always", "never"), default="never",
                      const="always", metavar="auto|always|never",
                      help="where links are drawn as hulls of their visual meshes (the default geometry of a robot "
                      "with meshes): end a warm-started frame's fit with Gauss-Newton steps drawn with the visual "
                      "meshes, its boundary offset fitted: auto when the meshes' loss at the hull fit's answer is "
                      "above --warm-outline-loss (a mask the hulls leave poorly explained: nearer on noisy masks at "
                      "1.6-3.6x the time, farther on a learned segmenter's), always (the option alone), never (default)")
    pose.add_argument("--warm-outline-loss", type=float, default=None, metavar="L",
                      help="that loss, with --warm-outline-polish auto or --warm-boundary-offset auto (default "
                      "0.08, the single-image fit's retry_outline_loss)")
    pose.add_argument("--warm-target", choices=("coverage", "threshold"), default="coverage",
                      help="what the mask term of warm-started frames and of --static-camera's refinement compares "
                      "the silhouette with at their working resolution: each pixel's coverage by the mask (default) "
                      "or the mask thresholded at half cover (as single-image fits, and the default until "
                      "2026-11-28)")
    pose.add_argument("--warm-calm", type=float, default=None, metavar="R",
                      help="fit each warm-started frame first with --warm-calm-iterations Adam steps at a tenth of "
                      "the warm rate, then the same polish, and the usual warm fit too only where that loss is "
                      "above R times the running loss (a jump); default: the usual warm fit alone. At R = 1.2 "
                      "nearer on tuning videos, nearer on 2 of 4 reported robots and farther on 2 (docs/tracking.md)")
    pose.add_argument("--warm-calm-iterations", type=int, default=5, metavar="N",
                      help="Adam steps of --warm-calm's fit (default 5)")
    pose.add_argument("--carry-moments", action=argparse.BooleanOptionalAction, default=True,
                      help="each warm fit's Adam begins with the state the last frame's fit ended with (default "
                      "on; --no-carry-moments: Adam from zeros, the default before 2026-12-07; docs/tracking.md)")
    pose.add_argument("--reinit-ratio", type=float, default=3.0, metavar="R",
                      help="fit a frame from scratch when its loss exceeds R times the running loss (default 3)")
    pose.add_argument("--reinit-limit", type=int, default=10, metavar="N",
                      help="after N frames in a row fitted from scratch, the running loss restarts at the last "
                      "frame's (default 10)")
    _add_drift_ratio(pose, "3")
    pose.add_argument(
        "--static-camera", action="store_true",
        help="the camera does not move relative to the robot's root: after the frames, refine one T_cam_root over "
        "them all (a trimmed sum of the frames' losses; written in the summary line)",
    )  # fmt: skip
    pose.add_argument("--static-frames", type=int, default=24, metavar="N",
                      help="--static-camera: at most N frames, evenly spread, take part (default 24)")
    pose.add_argument("--static-iterations", type=int, default=100, metavar="N",
                      help="--static-camera: Adam iterations of the joint refinement (default 100)")
    pose.add_argument("--static-polish-steps", type=int, default=10, metavar="N",
                      help="--static-camera: Levenberg-Marquardt steps on the frames' hard silhouettes after the "
                      "Adam iterations, each kept only where it lowers the loss (default 10; 0: none)")
    pose.add_argument("--static-outline-polish", action=argparse.BooleanOptionalAction, default=True,
                      help="--static-camera, where links are drawn as hulls of their visual meshes (the default "
                      "geometry of a robot with meshes): the polish draws the visual meshes, each frame's boundary "
                      "offset fitted (default on since session 49; --no-static-outline-polish: the polish draws the "
                      "hulls)")
    pose.add_argument("--static-trim", type=float, default=0.25, metavar="F",
                      help="--static-camera: share of the frames with the highest losses left out (default 0.25)")
    pose.add_argument("--static-running", action=argparse.BooleanOptionalAction, default=True,
                      help="--static-camera: also refine a running T_cam_root from the frames so far, once "
                      "--static-running-first frames are tracked and again each time their number doubles, and "
                      "write the latest in every line (static_T_cam_root; default on; --no-static-running: the "
                      "summary's estimate only)")
    pose.add_argument("--static-running-first", type=int, default=8, metavar="N",
                      help="--static-running: the first refinement after N tracked frames (default 8)")
    pose.add_argument("--smooth-window", type=int, default=SMOOTH_WINDOW, metavar="N",
                      help="for a moving camera: also write in every line the pose read off straight lines in time "
                      "through the last N tracked frames' poses (smooth_T_cam_root, smooth_frames; default "
                      f"{SMOOTH_WINDOW}: none; 6 is what the tuning videos suggest for masks whose outline errors change "
                      "from frame to frame)")
    _add_output_arguments(pose)
    add_segmenter_arguments(pose)
    pose.set_defaults(func=run_pose)


def run_shape(args: argparse.Namespace) -> int:
    import dataclasses

    from pipeline.camera import load_camera
    from pipeline.cli.shape import _parse_order, _parse_pixel, model_section_lengths
    from pipeline.errors import ConfigError
    from pipeline.robots import ContinuumRobot
    from pipeline.shape_estimation import ShapeFitConfig
    from pipeline.track import WARM_PCC_ITERATIONS, WARM_PREFIT_STEPS, ShapeTrackConfig, ShapeTracker

    camera = load_camera(args.camera)
    robot = ContinuumRobot(length_m=args.length, base_radius_m=args.base_radius, tip_radius_m=args.tip_radius)
    common = dict(seed=args.seed, keypoint_mode=args.keypoint_mode, keypoints=args.keypoints,
                  working_max_side=args.max_side)
    if args.rim_offset_px is None:  # 0, not image: on compressed video frames the readings were worse than none
        args.rim_offset_px = 0.0
    warm_rim = 0.0 if args.rim_offset_px in ("auto", "image") else args.rim_offset_px  # the tracker holds its own
    lengths = model_section_lengths(args, "--warm-pcc-iterations")
    live = args.live or args.device is not None
    if args.drop_late and not live:
        raise ConfigError("--drop-late drops the frames of a live source: add --live (or read a --device)")
    config = ShapeTrackConfig(
        full_fit=ShapeFitConfig(order=_parse_order(args.order), model=args.model, sections=args.sections,
                                section_lengths_m=lengths, iterations=args.iterations, starts=args.starts,
                                rim_offset_px=args.rim_offset_px, **common),
        warm_fit=dataclasses.replace(ShapeTrackConfig().warm_fit, iterations=args.warm_iterations,
                                     prefit_solver=args.warm_prefit_solver, prefit_iterations=(
                                         args.warm_prefit_iterations if args.warm_prefit_iterations is not None
                                         else WARM_PREFIT_STEPS[args.warm_prefit_solver]), compile=args.compile,
                                     warm_hypotheses=_parse_hypotheses(args.warm_hypotheses),
                                     warm_keep_start=args.warm_keep_start, rim_offset_px=warm_rim,
                                     warm_slow_start=(ShapeTrackConfig().warm_fit.warm_slow_start
                                                      if args.warm_slow_start is None else args.warm_slow_start),
                                     pcc_iterations=(WARM_PCC_ITERATIONS if args.warm_pcc_iterations is None
                                                     else args.warm_pcc_iterations), **common),
        reinit_ratio=args.reinit_ratio,
        drift_ratio=_parse_drift_ratio(args.drift_ratio),
        fixed_base=args.fixed_base,
        predict=args.predict,
        batch_frames=(8 if live else 1) if args.batch_frames is None else args.batch_frames, live=live,
        drop_late=args.drop_late,
        rim_search_frames=args.rim_search_frames,
        carry_moments=args.carry_moments,
    )
    base_pixel = _parse_pixel(args.base_pixel, "--base-pixel") if args.base_pixel is not None else None
    if args.segmenter in ("color", "onnx", "auto"):  # every component: the tracker chooses the arm's (docs/tracking.md)
        args.all_components = True
    tracker = ShapeTracker(robot, camera, config, base_pixel=base_pixel)
    _run_frames(args, "track shape", camera, tracker,
                step=lambda mask, index, time_s: tracker.step(mask, frame=index, time_s=time_s),
                step_many=lambda masks, indices, times: tracker.step_many(masks, frames=indices, times_s=times),
                batch=config.batch_frames, live=config.live, rim_search=config.full_fit.rim_offset_px == "auto",
                finish=lambda: _shape_summary(tracker),
                draw=lambda image, tracked: _shape_overlay(image, tracked, camera, robot))
    return 0


def _parse_hypotheses(text: str) -> tuple[int, ...]:
    """``--warm-hypotheses``: ``"none"`` or comma-separated indices >= 0."""
    from pipeline.errors import ConfigError

    if text.strip().lower() == "none":
        return ()
    try:
        values = tuple(int(item) for item in text.split(","))
    except ValueError:
        values = (-1,)
    if not values or min(values) < 0:
        raise ConfigError(f"--warm-hypotheses: expected 'none' or indices >= 0 such as 1 or 0,1, got {text!r}")
    return values


def _add_drift_ratio(parser: argparse.ArgumentParser, default: str, why: str = "") -> None:
    parser.add_argument("--drift-ratio", default=default, metavar="R|none",
                        help="fit a frame from scratch too when the running loss has climbed above R times its lowest "
                        f"since the track started (a track that starts wrong and gets worse slowly; none: off; "
                        f"default {default}{why})")


def _parse_drift_ratio(text: str) -> float | None:
    """``--drift-ratio``: ``"none"`` (off) or a number (``PoseTrackConfig`` checks that it is > 1)."""
    from pipeline.errors import ConfigError

    if text.strip().lower() == "none":
        return None
    try:
        return float(text)
    except ValueError:
        raise ConfigError(f"--drift-ratio: expected a number > 1 or 'none' (off), got {text!r}") from None


def run_pose(args: argparse.Namespace) -> int:
    import dataclasses

    from pipeline.camera import load_camera
    from pipeline.cli.pose import fit_config, load_model
    from pipeline.errors import ConfigError
    from pipeline.pose_estimation import PoseFitConfig, StaticCameraConfig
    from pipeline.track import RUNNING_STATIC, WARM_POSE_FIT, PoseTrackConfig, PoseTracker, calm_pose_fit

    camera = load_camera(args.camera)
    model = load_model(args)
    for name in ("static_frames", "static_iterations", "warm_iterations", "warm_max_side", "reinit_limit",
                 "static_running_first", "smooth_window", "warm_calm_iterations"):
        if getattr(args, name) < 1:
            raise ConfigError(f"--{name.replace('_', '-')}: expected an int >= 1, got {getattr(args, name)}")
    if args.static_polish_steps < 0:
        raise ConfigError(f"--static-polish-steps: expected an int >= 0, got {args.static_polish_steps}")
    if args.warm_calm is not None and not (args.warm_calm > 1.0 and math.isfinite(args.warm_calm)):
        raise ConfigError(f"--warm-calm: expected a finite number > 1 (times the running loss), got {args.warm_calm}")
    if args.interpolate_joints and args.joints_csv is None:
        raise ConfigError("--interpolate-joints goes with --joints-csv (per-frame readings)")
    if args.warm_outline_loss is not None and "auto" not in (args.warm_outline_polish, args.warm_boundary_offset):
        raise ConfigError(f"--warm-outline-loss is a setting of --warm-outline-polish auto or --warm-boundary-offset "
                          f"auto, but they are {args.warm_outline_polish} and {args.warm_boundary_offset}")
    joints_at = _joint_source(args, model)
    full = fit_config(args)
    outline_loss = PoseFitConfig().retry_outline_loss if args.warm_outline_loss is None else args.warm_outline_loss
    warm = dataclasses.replace(WARM_POSE_FIT, iterations=args.warm_iterations, working_max_side=args.warm_max_side,
                               polish_newton_steps=args.warm_newton_steps, weight_hidden=full.weight_hidden,
                               polish_boundary_offset=True if args.warm_boundary_offset == "always" else None,
                               offset_polish_loss=outline_loss if args.warm_boundary_offset == "auto" else None,
                               outline_polish=True if args.warm_outline_polish == "always" else None,
                               outline_polish_loss=outline_loss if args.warm_outline_polish == "auto" else None,
                               weight_appearance=full.weight_appearance,
                               coverage_target=args.warm_target == "coverage")
    static = StaticCameraConfig(iterations=args.static_iterations, max_frames=args.static_frames,
                                trim_fraction=args.static_trim, polish_steps=args.static_polish_steps,
                                coverage_target=args.warm_target == "coverage",
                                outline_polish=args.static_outline_polish,
                                fit=full) if args.static_camera else None
    running = None if static is None or not args.static_running else dataclasses.replace(
        static, iterations=min(RUNNING_STATIC.iterations, static.iterations), candidates=RUNNING_STATIC.candidates)
    tracker = PoseTracker(model, camera, PoseTrackConfig(
        full_fit=full, warm_fit=warm, reinit_ratio=args.reinit_ratio, reinit_limit=args.reinit_limit,
        drift_ratio=_parse_drift_ratio(args.drift_ratio), static_camera=static, running_static=running,
        running_static_first=args.static_running_first,
        smooth_window=None if args.smooth_window == 1 else args.smooth_window,
        calm_fit=None if args.warm_calm is None else calm_pose_fit(warm, args.warm_calm_iterations),
        carry_moments=args.carry_moments, **({} if args.warm_calm is None else {"calm_ratio": args.warm_calm})))

    def step(mask, index, time_s):
        return tracker.step(mask, joints_at(index, time_s), frame=index, time_s=time_s)

    def finish() -> dict:
        drift = {"drift_reinitialisations": tracker.drift_reinitialisations}
        if args.warm_calm is not None:
            drift["calm_fallbacks"] = tracker.calm_fallbacks
        if static is None:
            return drift
        result = tracker.static_estimate()
        kept = tracker.kept
        return {**drift, "T_cam_root": result.T_cam_root, "static_camera": {
            "loss": result.loss, "frames": [kept[i][0] for i in result.frames],
            "trimmed": [kept[i][0] for i in result.trimmed],
            "start_frame": kept[result.start][0],
            "iterations": result.iterations, "loss_before_polish": result.loss_before_polish,
            "polish_steps": result.polish_steps, "boundary_offsets_px": result.boundary_offsets_px.tolist(),
            "outline": result.outline,
            "seconds": result.seconds,
            **({"running_seconds": tracker.running_seconds} if running is not None else {})}}

    _run_frames(args, "track pose", camera, tracker, step=step, finish=finish,
                draw=lambda image, tracked: _pose_overlay(image, tracked, camera, model))
    return 0


def _joint_source(args: argparse.Namespace, model):
    """``joints_at(frame, time_s) -> (J,) tensor`` from ``--joints-csv`` (columns checked against the robot now)
    or the constant ``--joints`` / ``--joints-file``."""
    from pipeline.cli.pose import constant_joint_readings
    from pipeline.errors import ConfigError
    from pipeline.io import read_joints_csv

    if args.joints_csv is None:
        q = model.joint_vector(constant_joint_readings(args), zero_missing=args.zero_missing)
        return lambda index, time_s: q
    table = read_joints_csv(args.joints_csv, min_rows=2 if args.interpolate_joints else 1)
    unknown = [n for n in table.names if n not in model.description_joint_names]
    if unknown:
        raise ConfigError(f"{args.joints_csv}: column {unknown[0]!r} is no joint of {model.name} (columns: frame, "
                          f"time_s, and joints {', '.join(model.joint_names)})")
    missing = [n for n in model.joint_names if n not in table.names]
    if missing and not args.zero_missing:
        raise ConfigError(f"{args.joints_csv}: no column for joint(s) {', '.join(missing)} (every movable joint on "
                          "the way to a rendered link needs one; --zero-missing sets them to 0)")
    return lambda index, time_s: model.joint_vector(table.readings(index, time_s, interpolate=args.interpolate_joints),
                                                     zero_missing=args.zero_missing)


def _fit_seconds(tracked) -> float:
    """A frame's fitting time: its fit's, and a running static-camera refinement done after it."""
    static = getattr(tracked, "static", None)
    return tracked.seconds + (0.0 if static is None else static.seconds)


def _run_frames(args: argparse.Namespace, name: str, camera, tracker, *, step, draw, finish=None,
                step_many=None, batch: int = 1, live: bool = False, rim_search: bool = False) -> None:
    """The frame loop of both kinds: decode, segment, ``step(mask, index, time_s) -> tracked``, write the line and
    the overlay frame; then ``finish() -> dict`` (more summary fields) and the summary line. Frames that cannot be
    read go to ``tracker.skip``. With ``batch > 1``, up to ``batch`` segmented frames go to ``step_many(masks,
    indices, times) -> [tracked]`` together (an unreadable frame first flushes those before it, so that the lines
    stay in order). With ``live`` (a ``ShapeTracker``), a background thread reads and segments the frames
    (``pipeline.track.arrived_frames``) and each ``step_many`` takes the frames that arrived meanwhile, at most
    ``batch``; with ``args.drop_late`` the oldest waiting frame is dropped for the newest (a skipped line); Ctrl-C
    ends the run with its summary (``"interrupted": true``). With ``rim_search`` (a ``ShapeTracker``), frames are
    written only once its rim search is done (``rim_search_pending``), the searched ones as refitted
    (``rim_refits``)."""
    import time

    import numpy as np
    from tqdm.auto import tqdm

    from pipeline.camera import check_image_matches_camera
    from pipeline.cli._segmenter_args import segmenter_from_args
    from pipeline.errors import ConfigError

    segmenter = segmenter_from_args(args)
    if hasattr(tracker, "read_rim"):  # track shape: each frame's rim read by the tracker when it asks for it
        from pipeline.track import rim_reading

        segmenter = rim_reading(tracker, segmenter)
    source = _FrameSource(args)
    stages = {"decode": 0.0, "segment": 0.0, "fit": 0.0, "write": 0.0}
    out = open(args.out, "w", encoding="utf-8") if args.out is not None else None
    overlay = None
    frames = 0
    t_start = time.perf_counter()
    pending: list[tuple] = []  # (index, time_s, image, mask) segmented, not yet fitted (batch > 1)
    try:
        bar = tqdm(total=source.count, unit="frame", desc=name, disable=True if args.quiet else None)

        held: list[tuple] = []  # (image, tracked) done while the rim search waits for more frames

        def emit(image, tracked) -> None:  # the frame's line and overlay frame, or held until the rim search
            held.append((image, tracked))
            if not (rim_search and tracker.rim_search_pending):
                release()

        def release() -> None:  # the held frames, the searched ones as refitted
            if rim_search and tracker.rim_search is not None and any(t.frame in tracker.rim_refits for _, t in held):
                stages["fit"] += tracker.rim_search.seconds
            for image, tracked in held:
                write(image, tracker.rim_refits.get(tracked.frame, tracked) if rim_search else tracked)
            held.clear()

        def write(image, tracked) -> None:
            nonlocal overlay
            t = time.perf_counter()
            if out is not None:
                _write_line(out, tracked.to_dict())
            if args.overlay_video is not None:  # every frame, an unreadable one black (with a note)
                picture = image if image is not None else np.zeros((*camera.image_size, 3), np.uint8)
                overlay = overlay or _VideoWriter(args.overlay_video, source.fps or 10.0, picture.shape[:2])
                overlay.write(draw(picture, tracked))
            stages["write"] += time.perf_counter() - t
            bar.update(1)
            bar.set_postfix_str(f"{frames / (time.perf_counter() - t_start):.2f} fps")

        def flush() -> None:  # fit the pending frames together
            if not pending:
                return
            batch_out = step_many([p[3] for p in pending], [p[0] for p in pending], [p[1] for p in pending])
            for (_, _, image, _), tracked in zip(pending, batch_out):
                stages["fit"] += _fit_seconds(tracked)
                emit(image, tracked)
            pending.clear()

        def run_live() -> bool:  # the frames as they arrive; True when Ctrl-C stopped the run
            nonlocal frames
            from pipeline.track import DROPPED, arrived_frames

            def segmented(record, frame_index):  # the reader's thread (with --drop-late the fitting thread's)
                index, _, image, decode_seconds, error = record
                stages["decode"] += decode_seconds
                if error is not None:
                    return record, None
                check_image_matches_camera(image.shape[:2], camera)
                t = time.perf_counter()
                mask = segmenter(image, frame_index=index)
                stages["segment"] += time.perf_counter() - t
                return record, mask

            groups = arrived_frames(source.frames(), batch, segmented, drop_oldest=args.drop_late)
            try:
                for group in groups:
                    frames += len(group)
                    kept = [value for _, value in group if value is not None and value[1] is not None]
                    outcomes = step_many([mask for _, mask in kept], [record[0] for record, _ in kept],
                                         [record[1] for record, _ in kept]) if kept else []
                    done = {record[0]: tracked for (record, _), tracked in zip(kept, outcomes)}
                    for i, value in group:  # in frame order: fitted, unreadable and dropped frames
                        index = source.index_of(i)
                        time_s = source.time_of(index)
                        if value is None:
                            emit(None, tracker.skip(reason=DROPPED, frame=index, time_s=time_s))
                        elif value[0][4] is not None:
                            emit(None, tracker.skip(reason=value[0][4], frame=index, time_s=time_s))
                        else:
                            stages["fit"] += _fit_seconds(done[index])
                            emit(value[0][2], done[index])
            except KeyboardInterrupt:
                return True
            finally:
                groups.close()  # the reader thread stops at its next frame
            return False

        interrupted = False
        with bar:
            if live:
                interrupted = run_live()
            for index, time_s, image, decode_seconds, error in ([] if live else source.frames()):
                stages["decode"] += decode_seconds
                frames += 1
                if error is not None:
                    flush()
                    emit(image, tracker.skip(reason=error, frame=index, time_s=time_s))
                    continue
                check_image_matches_camera(image.shape[:2], camera)
                t = time.perf_counter()
                mask = segmenter(image, frame_index=index)
                stages["segment"] += time.perf_counter() - t
                if batch > 1:
                    pending.append((index, time_s, image, mask))
                    if len(pending) == batch or tracker.last is None:
                        flush()
                    continue
                tracked = step(mask, index, time_s)
                stages["fit"] += _fit_seconds(tracked)
                emit(image, tracked)
            flush()
            if rim_search and tracker.rim_search_pending:  # fewer frames than the search's (or none fitted)
                tracker.finish_rim_search()
            release()
        if frames == 0:
            raise ConfigError(f"no frame to track: {source.describe()} gave none between --start {args.start} and "
                              f"--stop {args.stop}")
        extra = finish() if finish is not None else {}
        seconds = time.perf_counter() - t_start
        summary = {"summary": True, "frames": frames, "skipped": tracker.skipped,
                   "reinitialisations": tracker.reinitialisations, "fps": frames / seconds, "seconds": seconds,
                   **{f"{stage}_seconds": value for stage, value in stages.items()}, **extra,
                   **({"interrupted": True} if interrupted else {})}
        if out is not None:
            _write_line(out, summary)
    finally:
        source.close()
        if out is not None:
            out.close()
        if overlay is not None:
            overlay.close()
    static = ""
    if "static_camera" in summary:
        t = summary["T_cam_root"][:3, 3]
        static = (f"; static camera T_cam_root t = ({t[0]:.4f}, {t[1]:.4f}, {t[2]:.4f}) m from "
                  f"{len(summary['static_camera']['frames'])} frames")
    print(f"{name}: {frames} frames ({tracker.skipped} skipped, {tracker.reinitialisations} re-initialised) at "
          f"{summary['fps']:.2f} frames/s; decode {stages['decode']:.2f} s, segment {stages['segment']:.2f} s, "
          f"fit {stages['fit']:.2f} s, write {stages['write']:.2f} s" + static
          + (f"; rim offset {summary['rim_offset_px']:+g} px (searched)" if summary.get("rim_offset_losses") else "")
          + (f"; rim offset {summary['rim_offset_px']:+.2f} px (read from {len(summary['rim_offset_readings'])} "
             f"frames)" if summary.get("rim_offset_readings") else "")
          + (f"; wrote {args.out}" if args.out else ""))


def _shape_summary(tracker) -> dict:
    """The summary's own fields of ``track shape``: the re-initialisations the drift rule made, the rim offset held
    and, when it was searched, the frames' mean loss at each offset tried."""
    import numpy as np

    drift = {"drift_reinitialisations": tracker.drift_reinitialisations}
    search = tracker.rim_search
    held = tracker.rim_offset if tracker.rim_offset is not None else tracker.config.full_fit.known_rim_offset_px
    if tracker.config.full_fit.rim_offset_px == "image":
        readings = list(tracker.rim_readings)
        return {**drift, "rim_offset_px": float(np.median(readings)) if readings else 0.0,
                "rim_offset_readings": readings}
    return {**drift, "rim_offset_px": held, "rim_offset_losses": None if search is None else
            {repr(float(offset)): loss for offset, loss in search.losses.items()}}


def _write_line(out, record: dict) -> None:
    from pipeline.io import json_line

    out.write(json_line(record) + "\n")
    out.flush()


def _shape_overlay(image, tracked, camera, robot):
    from pipeline.camera import undistort_image
    from pipeline.shape_estimation import draw_shape_overlay

    background = undistort_image(image, camera)[0]
    if tracked.result is None:
        return _skipped_frame(background, tracked)
    return draw_shape_overlay(background, tracked.result, robot)


def _pose_overlay(image, tracked, camera, model):
    from pipeline.camera import undistort_image
    from pipeline.pose_estimation import draw_pose_overlay

    if tracked.result is None:
        return _skipped_frame(undistort_image(image, camera)[0], tracked)
    return draw_pose_overlay(image, model, tracked.result, camera)


def _skipped_frame(background, tracked):
    import cv2

    out = background.copy()
    cv2.putText(out, f"frame {tracked.frame}: skipped", (10, 25), cv2.FONT_HERSHEY_SIMPLEX, 0.7, (0, 0, 255), 2)
    return out


class _VideoWriter:
    """``cv2.VideoWriter`` (mp4v) that raises ``ConfigError`` when the file cannot be opened."""

    def __init__(self, path: str, fps: float, image_size: tuple[int, int]) -> None:
        import cv2

        from pipeline.errors import ConfigError

        H, W = image_size
        self.writer = cv2.VideoWriter(path, cv2.VideoWriter_fourcc(*"mp4v"), fps, (W, H))
        if not self.writer.isOpened():
            raise ConfigError(f"--overlay-video {path}: OpenCV cannot write this file (use a .mp4 path in an "
                              "existing folder)")

    def write(self, image) -> None:
        self.writer.write(image)

    def close(self) -> None:
        self.writer.release()


class _FrameSource:
    """Frames ``--start``, ``--start + --step``, ... before ``--stop`` of a video or a sorted list of image files.

    ``frames()`` yields ``(index, time_s, image or None, decode_seconds, error or None)``: an image that cannot be
    read gives ``error`` (the frame is skipped; tracking goes on).
    """

    def __init__(self, args: argparse.Namespace) -> None:
        import glob

        import cv2

        from pipeline.errors import AssetError, ConfigError

        for name in ("start", "step"):
            low = 0 if name == "start" else 1
            if getattr(args, name) < low:
                raise ConfigError(f"--{name}: expected an int >= {low}, got {getattr(args, name)}")
        if args.stop is not None and args.stop <= args.start:
            raise ConfigError(f"--stop: expected a frame after --start {args.start}, got {args.stop}")
        if args.fps is not None and not args.fps > 0:
            raise ConfigError(f"--fps: expected a number > 0, got {args.fps}")
        self.start, self.stop, self.step = args.start, args.stop, args.step
        self.video = args.video
        self.device = getattr(args, "device", None)
        self.capture = None
        self.files: list[str] = []
        self.fps = args.fps
        self.read_at: dict[int, float] = {}  # --device: each frame's time since the first, until asked for
        if self.device is not None:
            self.capture = cv2.VideoCapture(self.device)
            if not self.capture.isOpened():
                raise AssetError(f"--device {self.device}: OpenCV cannot open camera {self.device} (is it connected "
                                 "and not in use by another program?)")
            total = None
        elif args.video is not None:
            from pathlib import Path

            if not Path(args.video).is_file():
                raise AssetError(f"--video {args.video}: no such file")
            self.capture = cv2.VideoCapture(args.video)
            if not self.capture.isOpened():
                raise AssetError(f"--video {args.video}: OpenCV cannot open it as a video")
            total = int(self.capture.get(cv2.CAP_PROP_FRAME_COUNT))
            if self.fps is None and self.capture.get(cv2.CAP_PROP_FPS) > 0:
                self.fps = float(self.capture.get(cv2.CAP_PROP_FPS))
        else:
            self.files = sorted(glob.glob(args.frames))
            if not self.files:
                raise AssetError(f"--frames {args.frames!r}: no file matches")
            total = len(self.files)
        end = total if self.stop is None or total is None else min(total, self.stop)
        if end is None:
            end = self.stop
        self.count = max(0, (end - self.start + self.step - 1) // self.step) if end else None

    def describe(self) -> str:
        if self.device is not None:
            return f"--device {self.device}"
        return f"--video {self.video}" if self.video is not None else f"--frames ({len(self.files)} files)"

    def index_of(self, i: int) -> int:
        """The frame number of the ``i``-th frame ``frames()`` yields (0, 1, ...)."""
        return self.start + i * self.step

    def time_of(self, index: int) -> float | None:
        """Frame ``index``'s ``time_s`` (a ``--device`` frame's once; ``None`` for one not read)."""
        return self.read_at.pop(index, None) if self.device is not None else self._time(index)

    def frames(self):
        import time

        from pipeline.errors import AssetError
        from pipeline.io import read_image

        if self.capture is None:
            for index in range(self.start, len(self.files) if self.stop is None else min(self.stop, len(self.files)),
                               self.step):
                t = time.perf_counter()
                try:
                    image, error = read_image(self.files[index]), None
                except AssetError as e:
                    image, error = None, f"unreadable frame: {e}"
                yield index, self._time(index), image, time.perf_counter() - t, error
            return
        index, first = 0, None
        while self.stop is None or index < self.stop:
            t = time.perf_counter()
            wanted = index >= self.start and (index - self.start) % self.step == 0
            if not wanted:
                if not self.capture.grab():  # skip without decoding
                    return
                index += 1
                continue
            ok, image = self.capture.read()
            if not ok:
                return
            if self.device is not None:  # its time kept until the frame's line asks for it (time_of)
                now = time.perf_counter()
                first = now if first is None else first
                self.read_at[index] = now - first
            yield index, self.read_at.get(index, self._time(index)), image, time.perf_counter() - t, None
            index += 1

    def _time(self, index: int) -> float | None:
        return None if self.fps is None else index / self.fps

    def close(self) -> None:
        if self.capture is not None:
            self.capture.release()
