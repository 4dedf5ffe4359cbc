"""Frames per second of ``pipeline track shape`` on a synthetic 640x360 video, per stage, and its accuracy.

A moving soft arm (``pipeline.synth.soft_arm.moving_bezier_arm``: base fixed, every joint bending one way then
the other; ``--order 3`` gives S shapes) drawn area-averaged over a static cluttered background (the drawn arm
has the true mask's area), written as an MJPG video with its true centrelines. The video is tracked through the
command line (``pipeline track shape --video ...``, segmented by ``--segmenter``: the arm's colour preset (the
default here), ``auto`` (the command's own default) or the true masks as files; default settings unless given),
whose summary line gives frames per second and the seconds spent decoding, segmenting, fitting and writing. Then
the accuracy: the mean 2D / 3D centreline error of every tracked frame against the truth, and, on every
``--single-every``-th frame, the tracked error against an independent full single-frame fit of the same mask as
the tracker's (the segmented decoded frame, or the true mask) (``reconstruct_shape`` with default settings).
Timings on a shared machine vary with its load: the script prints the load average.

    python benchmarks/bench_track.py [--frames 100] [--width 640 --height 360] [--order 2] [--single-every 10]
        [--tensor-loss]

Clutter and occlusion (``docs/tracking.md``): ``--distractor 1.5 [--distractor-from F]`` draws a shaded ellipse of
the arm's colour, 1.5x the arm's mean area, where the arm never comes (from frame F on); ``--occluder 12`` a grey
band 12 px wide in front of the arm, across the first frame's arm and square to it. ``--keep DIR`` keeps the video,
masks and JSONL (and, for ``--kind pose``, the truth: ``truth.npz`` with ``T_cam_root`` ``(F, 4, 4)``,
``end_effector_root`` ``(F, 3)`` and ``joints``).

``--kind pose``: a manipulator (``--robot``: the bundled toy arm, or Panda, UR5 or Baxter's left arm from the
``example-robot-data`` package, ``pip install .[robots]``, or one of its arms held out from the defaults' choice)
whose joints move between two random configurations (``pipeline.synth.pose.manipulator_sequence``), under a fixed
camera (``--orbit 0``) or a camera orbiting slowly about the robot (``--orbit DEG`` per frame); shaded frames over clutter written as an MJPG video (decoded and timed
by the command), masks drawn by the painter's renderer (``pipeline.synth.pose.painter_mask``, not the fit's) with
``--noise`` (a wobbly boundary and a 1 px dilation or erosion, alternating; every other single-frame pick is then
moved on by a frame, so both kinds are compared, each also on its own; ``--noise-bias dilate|erode``: the same
bias on every frame, a segmenter's steady error) and read with ``--segmenter file``, or
(``--segmenter onnx``) the command's default, the shipped network, segments the decoded frames itself (the
single-frame fits get the same network's masks; its IoU with the painter's is printed); the joints as
``joints.csv``. Tracked by ``pipeline track pose`` (with ``--static-camera`` when the camera is fixed);
printed: per-stage times, frames per second, the end effector's (``tcp``) 3D / 2D error per tracked frame, against
independent full single-frame fits (``estimate_pose`` defaults) of every ``--single-every``-th frame, and the
static-camera estimate's error against the median single-frame error. A real robot's frames and masks are drawn
from its visual meshes simplified by the loader's CAD budget (``primitive="cad"``; the full meshes take seconds a
frame), the fit renders the command's default geometry (``--primitive auto``: convex hulls) unless
``-- --primitive ...`` says otherwise; its end effector is the acceptance benchmark's (``acceptance_robots.ROBOTS``).

    python benchmarks/bench_track.py --kind pose --frames 30 --orbit 0 --seed 21 [-- TRACK_POSE_OPTIONS]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import tempfile
from pathlib import Path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--kind", choices=("shape", "pose"), default="shape", help="soft arm or manipulator")
    parser.add_argument("--frames", type=int, default=100)
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=360)
    parser.add_argument("--order", default="2",
                        help="shape: the moving Bezier arm's order (--arm bezier), and the fits' (or auto)")
    parser.add_argument("--arm", choices=("bezier", "pcc"), default="bezier",
                        help="shape: the moving arm, a Bezier curve of --order (default) or two 100 mm "
                        "constant-curvature sections (curvature up to 15 1/m each, planes swinging)")
    parser.add_argument("--model", choices=("bezier", "pcc"), default="bezier",
                        help="shape: the tracker's and the single-frame fits' model (pcc: two sections; the mean "
                        "curvature error is printed for --arm pcc)")
    parser.add_argument("--section-lengths", metavar="L1,L2", help="shape, --model pcc: the sections' lengths")
    parser.add_argument("--period", type=float, default=50.0, help="frames per bending (joint) cycle")
    parser.add_argument("--orbit", type=float, default=0.0, help="pose: camera orbit, degrees per frame (0: fixed)")
    parser.add_argument("--handheld", type=float, default=0.0, metavar="DEG",
                        help="pose: the camera also sways as a hand-held one does, DEG degrees and DEG cm at most "
                        "per component (manipulator_sequence's handheld_deg; the camera then moves: no "
                        "--static-camera)")
    parser.add_argument("--robot", default="toy",
                        choices=("toy", "panda", "ur5", "baxter", "kinova", "xarm7", "z1", "so100", "pr2", "icub",
                                 "talos"),
                        help="pose: the bundled toy arm, or a real robot of example-robot-data (kinova, xarm7, z1, "
                        "so100, pr2, icub, talos: acceptance_robots.HELD_OUT, no default was chosen on them)")
    parser.add_argument("--noise", action="store_true", help="pose: segmenter-like noise on the masks")
    parser.add_argument("--noise-bias", choices=("alternate", "dilate", "erode"), default="alternate",
                        help="pose, with --noise: the 1 px outline bias on alternate frames (eroded even frames, "
                        "dilated odd ones: the default), or the same on every frame (a segmenter's steady bias)")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--single-every", type=int, default=10)
    parser.add_argument("--segmenter", choices=("color", "auto", "file", "onnx"), default=None,
                        help="shape (default color): color: segment the decoded frames with the arm's colour preset; "
                        "auto: with the command's default segmenter (the shipped network refined by GrabCut); file: "
                        "the true masks, written as PNGs. pose (default file: the painter's masks, --noise applies): "
                        "onnx: the command's default segmenter, the shipped network, on the decoded frames")
    parser.add_argument("--distractor", type=float, default=0.0, metavar="AREA",
                        help="shape: a shaded ellipse of the arm's colour, AREA times the arm's mean mask area, drawn "
                        "where the arm never comes (clutter a segmenter marks as the arm; 0: none)")
    parser.add_argument("--distractor-from", type=int, default=0, metavar="FRAME",
                        help="shape: the first frame with the distractor (it stays after)")
    parser.add_argument("--occluder", type=float, default=0.0, metavar="PX",
                        help="shape: a grey band PX wide (at 640x360; scaled with the width) in front of the arm, "
                        "across the image through the middle of the first frame's arm and square to it, in every "
                        "frame (the truth is the whole arm; 0: none)")
    parser.add_argument("--keep", metavar="DIR", help="write the video, masks, camera and JSONL to DIR and keep them "
                        "(default: a temporary folder)")
    parser.add_argument("--per-frame", action="store_true",
                        help="shape: also print each picked frame's tracked and single-frame errors and losses")
    parser.add_argument("--tensor-loss", action="store_true",
                        help="shape: the rendered loss as tensor operations (shape_estimation.FUSED_LOSS = False, "
                        "the path before 2026-12-07), for the ratio against a run without it")
    parser.add_argument("track_options", nargs="*", help="extra options for track shape (after --)")
    args = parser.parse_args()
    if args.tensor_loss:
        from pipeline import shape_estimation

        shape_estimation.FUSED_LOSS = False
    allowed = ("file", "onnx") if args.kind == "pose" else ("color", "auto", "file")
    if args.segmenter is None:
        args.segmenter = "file" if args.kind == "pose" else "color"
    if args.segmenter not in allowed:
        parser.error(f"--segmenter {args.segmenter}: --kind {args.kind} takes {', '.join(allowed)}")
    if args.kind == "pose":
        bench_pose(args)
    else:
        bench_shape(args)


@contextlib.contextmanager
def work_folder(keep: str | None):
    """``keep`` (created), or a temporary folder removed afterwards."""
    if keep is not None:
        Path(keep).mkdir(parents=True, exist_ok=True)
        yield keep
        return
    with tempfile.TemporaryDirectory() as tmp:
        yield tmp


def run_track(argv: list[str], out: Path) -> tuple[dict, list[dict]]:
    """Run ``python -m pipeline`` with ``argv`` in this process (exit on failure); its JSONL ``out`` as (summary
    line, frame lines)."""
    from pipeline.cli import main as cli

    code = cli(argv)
    if code != 0:
        raise SystemExit(code)
    lines = [json.loads(line) for line in out.read_text().splitlines()]
    return lines[-1], lines[:-1]


def print_timing(summary: dict, frames: list[dict]) -> None:
    """Frames per second, the warm-started frames' fit time and the per-stage seconds of a track's JSONL lines."""
    import numpy as np

    n = summary["frames"]
    print(f"all frames: {summary['fps']:.3f} frames/s ({summary['skipped']} skipped, "
          f"{summary['reinitialisations']} re-initialised" + (
              f", {summary['drift_reinitialisations']} by the drift rule" if "drift_reinitialisations" in summary
              else "") + (f", {summary['calm_fallbacks']} calm fits fell back" if "calm_fallbacks" in summary
                          else "") + ")")
    warm = [line["seconds"] for line in frames[1:] if line["skipped"] is None and not line["reinitialised"]]
    print(f"warm-started frames: fit {np.median(warm):.3f} s median per frame -> {1.0 / np.median(warm):.2f} "
          f"frames/s for the fit alone; first frame (full fit) {frames[0]['seconds']:.2f} s")
    print("per stage, seconds per frame: " + ", ".join(
        f"{stage} {summary[stage + '_seconds'] / n:.4f}" for stage in ("decode", "segment", "fit", "write")))


def bench_shape(args: argparse.Namespace) -> None:
    import cv2
    import numpy as np

    from pipeline.evaluate import centerline_errors
    from pipeline.io import write_json, write_mask
    from pipeline.robots import ContinuumRobot
    from pipeline.segment import color_preset, make_segmenter
    from pipeline.segment.refine import AutoSegmenterConfig
    from pipeline.shape_estimation import ShapeFitConfig, reconstruct_shape
    from pipeline.synth.soft_arm import render_tube_image

    H, W = args.height, args.width
    camera, swept, truths, curvatures = moving_arm(args)
    K = camera.K_array()
    radii = np.linspace(0.014, 0.006, len(truths[0]))
    with work_folder(args.keep) as tmp:
        folder = Path(tmp)
        write_json(folder / "camera.json", camera.to_dict())
        writer = cv2.VideoWriter(str(folder / "arm.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 25.0, (W, H))
        true_masks = []
        distractor = distractor_disc(swept, radii, K, (H, W), args.distractor) if args.distractor > 0 else None
        for i, truth in enumerate(truths):
            image, mask = render_tube_image(truth, radii, K, (H, W), np.random.default_rng(0), supersample=4)
            if distractor is not None and i >= args.distractor_from:
                draw_distractor(image, mask, *distractor, np.random.default_rng(i))
            if args.occluder > 0:
                draw_occluder(image, truths[0], K, args.occluder * W / 640.0, np.random.default_rng(i))
            writer.write(image)
            write_mask(folder / "masks" / f"{i:05d}.png", mask)
            true_masks.append(mask)
        writer.release()
        if args.segmenter == "file":
            masks = true_masks
            segmenter_options = ["--segmenter", "file", "--mask-pattern", str(folder / "masks" / "{frame:05d}.png")]
        else:  # the masks the tracker sees: the segmenter on the decoded (compressed) frames, every component kept
            segment = make_segmenter(color_preset("soft_arm", largest_component=False) if args.segmenter == "color"
                                     else AutoSegmenterConfig(largest_component=False))
            capture, masks = cv2.VideoCapture(str(folder / "arm.avi")), []
            while (frame := capture.read())[0]:
                masks.append(segment(frame[1], frame_index=len(masks)))
            segmenter_options = ["--segmenter", args.segmenter]
        out = folder / "traj.jsonl"
        model_options = ["--model", args.model] + (["--section-lengths", args.section_lengths]
                                                   if args.section_lengths else [])
        argv = ["track", "shape", "--camera", str(folder / "camera.json"), "--video", str(folder / "arm.avi"),
                "--length", "0.2", "--base-radius", "0.014", "--tip-radius", "0.006", "--order", str(args.order),
                *model_options, "--out", str(out), "--quiet", *segmenter_options, *args.track_options]
        summary, frames = run_track(argv, out)
    n = summary["frames"]
    if args.distractor > 0:
        print(f"distractor: {args.distractor:g} x the arm's area, from frame {args.distractor_from}")
    if args.occluder > 0:
        print(f"occluder: a grey band {args.occluder * W / 640.0:g} px wide across the first frame's arm")
    print(f"{W}x{H}, {n} frames, {args.arm} arm, order {args.order}, model {args.model}, {args.segmenter} segmenter, "
          f"options "
          f"{args.track_options or 'default'}; "
          f"load average {os.getloadavg()[0]:.2f}")
    print_timing(summary, frames)
    errors = np.array([[centerline_errors(np.array(line["centerline_cam_m"]), truths[line["frame"]], K)[key]
                        for key in ("mean_2d_px", "mean_3d_mm")] for line in frames if line["skipped"] is None])
    print(f"tracked, all frames: mean 2D {errors[:, 0].mean():.2f} px (max {errors[:, 0].max():.2f}), mean 3D "
          f"{errors[:, 1].mean():.2f} mm (max {errors[:, 1].max():.2f})")
    bends = None
    if args.model == "pcc" and curvatures is not None:
        bends = {line["frame"]: np.abs(np.array(line["pcc"]["curvatures_per_m"]) - curvatures[line["frame"]])
                 for line in frames if line["skipped"] is None}
        print(f"tracked curvatures: mean error {np.mean(list(bends.values())):.2f} 1/m (truth up to 15 1/m)")
    robot = ContinuumRobot(length_m=0.2, base_radius_m=0.014, tip_radius_m=0.006)
    picked = list(range(0, len(frames), args.single_every))
    lengths = tuple(float(x) for x in args.section_lengths.split(",")) if args.section_lengths else ()
    fit_config = ShapeFitConfig(order=args.order if args.order == "auto" else int(args.order), model=args.model,
                                section_lengths_m=lengths)
    fits = {i: reconstruct_shape(masks[i], robot, camera, fit_config) for i in picked}
    single = np.array([[centerline_errors(fits[i].centerline_cam_m, truths[i], K)[key]
                        for key in ("mean_2d_px", "mean_3d_mm")] for i in picked])
    print(f"frames {picked[0]}, {picked[1] if len(picked) > 1 else ''}... ({len(picked)}): tracked mean 2D "
          f"{errors[picked, 0].mean():.2f} px / 3D {errors[picked, 1].mean():.2f} mm; independent single-frame fits of the same masks "
          f"{single[:, 0].mean():.2f} px / {single[:, 1].mean():.2f} mm")
    if args.per_frame:
        print("frame: tracked 2D px / 3D mm / loss | single-frame fit 2D px / 3D mm / loss")
        for j, i in enumerate(picked):
            print(f"{i:5d}: {errors[i, 0]:6.2f} / {errors[i, 1]:6.2f} / {frames[i]['loss']:.4f} | "
                  f"{single[j, 0]:6.2f} / {single[j, 1]:6.2f} / {fits[i].loss:.4f}")
    if bends is not None:
        print(f"  curvatures on those frames: tracked {np.mean([bends[i] for i in picked if i in bends]):.2f} 1/m, "
              f"single-frame fits {np.mean([np.abs(fits[i].pcc.curvatures_per_m - curvatures[i]) for i in picked]):.2f}"
              " 1/m")


def moving_arm(args: argparse.Namespace):
    """The benchmark's moving soft arm (``--width``, ``--height``, ``--frames``, ``--order``, ``--period``,
    ``--seed``, ``--arm``): ``(camera, a centreline (60, 3) per frame for the distractor's place, true centrelines
    (201 or 101, 3) per frame, true curvatures (T, 2) of a constant-curvature arm or None)``, the camera with the
    acceptance set-up's field of view (1280x720, fx 700)."""
    import numpy as np

    from pipeline.camera import Camera
    from pipeline.shapes.polyline import bezier_centerline
    from pipeline.synth.soft_arm import moving_bezier_arm, moving_pcc_arm

    H, W = args.height, args.width
    f = 700.0 * W / 1280.0
    K = np.array([[f, 0.0, (W - 1) / 2], [0.0, f, (H - 1) / 2], [0.0, 0.0, 1.0]])
    camera = Camera(K=K.tolist(), width=W, height=H)
    if getattr(args, "arm", "bezier") == "pcc":
        centrelines, curvatures, _ = moving_pcc_arm(np.random.default_rng(args.seed), K, (H, W), args.frames,
                                                    period_frames=args.period)
        return camera, [c[::2] for c in centrelines], list(centrelines), curvatures
    if str(args.order) == "auto":
        raise SystemExit("--order auto: the moving Bezier arm needs an order (use --arm pcc, or a number)")
    control = moving_bezier_arm(np.random.default_rng(args.seed), K, (H, W), args.frames, order=int(args.order),
                                period_frames=args.period)
    return camera, [bezier_centerline(c, 60) for c in control], [bezier_centerline(c, 201) for c in control], None


def distractor_disc(centrelines, radii, K, image_size, area_ratio):
    """``(centre (u, v), axes (a, b) px, angle deg)`` of an ellipse ``area_ratio`` times the arm's mean projected
    area, centred where the arm's tubes over the whole video are farthest (a few frames' centrelines, widened)."""
    import cv2
    import numpy as np

    H, W = image_size
    swept, area = np.zeros((H, W), np.uint8), 0.0
    for points in centrelines[:: max(len(centrelines) // 25, 1)]:
        uv = points @ K.T
        uv = uv[:, :2] / uv[:, 2:]
        width = K[0, 0] * float(np.mean(radii)) / points[:, 2].mean()
        cv2.polylines(swept, [np.round(uv).astype(np.int32)], False, 1, thickness=max(int(2 * width + 8), 1))
        area += float(np.linalg.norm(np.diff(uv, axis=0), axis=1).sum()) * 2 * width
    area /= len(centrelines[:: max(len(centrelines) // 25, 1)])
    b = math.sqrt(area_ratio * area / (math.pi * 1.8))
    far = cv2.distanceTransform((swept == 0).astype(np.uint8), cv2.DIST_L2, 5)
    edge = min(int(math.ceil(1.8 * b)) + 2, H // 2 - 1, W // 2 - 1)  # the whole ellipse in the image
    far[:edge], far[H - edge:], far[:, :edge], far[:, W - edge:] = -1, -1, -1, -1
    v, u = np.unravel_index(int(np.argmax(far)), far.shape)
    return (float(u), float(v)), (1.8 * b, b), 30.0


def draw_distractor(image, mask, centre, axes, angle, generator) -> None:
    """Draw the distractor ellipse (the arm's colour, shaded towards its rim, light noise) where ``mask`` is not."""
    import cv2
    import numpy as np

    from pipeline.synth.soft_arm import DEFAULT_ARM_COLOR_BGR

    H, W = mask.shape
    blob = np.zeros((H, W), np.uint8)
    cv2.ellipse(blob, (round(centre[0]), round(centre[1])), (round(axes[0]), round(axes[1])), angle, 0, 360, 1, -1)
    inside = cv2.distanceTransform(blob, cv2.DIST_L2, 5)
    shade = 0.55 + 0.45 * np.clip(inside / max(float(inside.max()), 1.0), 0.0, 1.0)
    colour = np.clip(np.asarray(DEFAULT_ARM_COLOR_BGR, float)[None, None] * shade[..., None]
                     + generator.normal(0.0, 3.0, (H, W, 3)), 0, 255).astype(np.uint8)
    where = (blob > 0) & ~mask
    image[where] = colour[where]


def draw_occluder(image, first_centerline, K, width_px, generator) -> None:
    """A grey band ``width_px`` wide across the whole image, through the projected midpoint of the first frame's
    centreline and square to it there (in front of the arm: the arm's mask, and the truth, are unchanged), with
    light noise."""
    import numpy as np

    uv = first_centerline @ K.T
    uv = uv[:, :2] / uv[:, 2:]
    middle = len(uv) // 2
    tangent = uv[middle + 1] - uv[middle - 1]
    tangent /= max(float(np.linalg.norm(tangent)), 1e-9)
    H, W = image.shape[:2]
    v, u = np.mgrid[0:H, 0:W]
    band = np.abs((u - uv[middle, 0]) * tangent[0] + (v - uv[middle, 1]) * tangent[1]) <= width_px / 2
    grey = 128.0 + generator.normal(0.0, 3.0, (int(band.sum()), 3))
    image[band] = np.clip(np.round(grey), 0, 255).astype(np.uint8)


def bench_pose(args: argparse.Namespace) -> None:
    import cv2
    import numpy as np
    import torch

    from pipeline.camera import Camera
    from pipeline.evaluate import point_errors
    from pipeline.io import write_json, write_mask
    from pipeline.pose_estimation import PoseFitConfig, estimate_pose
    from pipeline.robots import load_robot
    from pipeline.synth.pose import corrupt_mask, manipulator_sequence, painter_mask, render_robot_image

    H, W = args.height, args.width
    f = 500.0 * W / 640.0
    camera = Camera(K=((f, 0.0, (W - 1) / 2), (0.0, f, (H - 1) / 2), (0.0, 0.0, 1.0)), width=W, height=H)
    if args.robot == "toy":
        urdf, root, end_effector = Path(__file__).resolve().parents[1] / "models/robots/toy_arm/toy_arm.urdf", \
            "base_link", "tcp"
        model = load_robot(urdf, root)
    else:
        from acceptance_robots import ROBOTS

        urdf, root, end_effector = ROBOTS[args.robot].path, ROBOTS[args.robot].root, ROBOTS[args.robot].end_effector
        if not urdf.is_file():
            raise SystemExit(f"{urdf} missing: pip install .[robots]")
        model = load_robot(urdf, root, primitive="cad", outline=False)  # the truth: visual meshes, drawn by the painter
    options = args.track_options
    primitive = options[options.index("--primitive") + 1] if "--primitive" in options else "auto"
    fit_model = model if args.robot == "toy" else load_robot(urdf, root, primitive=primitive)  # the command's
    joints, poses = manipulator_sequence(model, camera, np.random.default_rng(args.seed), args.frames,
                                         orbit_deg_per_frame=args.orbit, period_frames=args.period,
                                         fill_range=(0.7, 0.9), handheld_deg=args.handheld)
    rng = np.random.default_rng(args.seed + 1000)
    masks, clean_masks = [], []
    for i, (q, T) in enumerate(zip(joints, poses)):
        mask = painter_mask(model, q, T, camera)
        clean_masks.append(mask)
        if args.noise:
            mask = corrupt_mask(mask, rng, boundary_noise_px=1.0 * W / 640)
            dilated = i % 2 == 1 if args.noise_bias == "alternate" else args.noise_bias == "dilate"
            mask = (cv2.dilate if dilated else cv2.erode)(mask.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
        masks.append(mask)
    tcp = model.frame_index(end_effector)
    points = np.stack([model.link_frames_in_root(torch.from_numpy(q)[None])[0, tcp, :3, 3].numpy() for q in joints])

    def errors(T_est, frames):
        e = point_errors(np.asarray(T_est), poses[frames], points[frames], camera.K_array())
        return e["err_3d_mm"], e["err_2d_px"]

    static = args.orbit == 0.0 and args.handheld == 0.0
    with work_folder(args.keep) as tmp:
        folder = Path(tmp)
        write_json(folder / "camera.json", camera.to_dict())
        np.savez(folder / "truth.npz", T_cam_root=np.asarray(poses), end_effector_root=points, joints=joints)
        writer = cv2.VideoWriter(str(folder / "arm.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 25.0, (W, H))
        for i, (q, T) in enumerate(zip(joints, poses)):
            writer.write(render_robot_image(model, q, T, camera, np.random.default_rng(args.seed))[0])
            write_mask(folder / "masks" / f"{i:05d}.png", masks[i])
        writer.release()
        rows = ["frame,time_s," + ",".join(model.joint_names)]
        rows += [f"{i},{i / 25.0}," + ",".join(repr(float(v)) for v in q) for i, q in enumerate(joints)]
        (folder / "joints.csv").write_text("\n".join(rows) + "\n")
        out = folder / "traj.jsonl"
        segmenter_options = ["--segmenter", "file", "--mask-pattern", str(folder / "masks" / "{frame:05d}.png")]
        if args.segmenter == "onnx":  # the masks the tracker sees: the shipped network on the decoded frames
            from pipeline.segment import make_segmenter
            from pipeline.segment.onnx_model import OnnxSegmenterConfig

            segment = make_segmenter(OnnxSegmenterConfig())
            capture, masks = cv2.VideoCapture(str(folder / "arm.avi")), []
            while (frame := capture.read())[0]:
                masks.append(segment(frame[1], frame_index=len(masks)))
            iou = [float((m & t).sum() / max((m | t).sum(), 1)) for m, t in zip(masks, clean_masks)]
            area = [float(m.sum() / max(t.sum(), 1)) for m, t in zip(masks, clean_masks)]
            segmenter_options = ["--segmenter", "onnx"]
        argv = ["track", "pose", "--camera", str(folder / "camera.json"), "--video", str(folder / "arm.avi"),
                "--robot", str(urdf), "--root", root, "--joints-csv", str(folder / "joints.csv"),
                *segmenter_options, "--out", str(out), "--quiet", *(["--static-camera"] if static else []),
                *args.track_options]
        summary, frames = run_track(argv, out)
    n = summary["frames"]
    robot_text = "toy arm" if args.robot == "toy" else f"{args.robot} (fit: --primitive {primitive})"
    print(f"{W}x{H}, {n} frames, {robot_text}, camera {'fixed' if static else f'orbiting {args.orbit} deg/frame'}"
          f"{f', hand-held sway {args.handheld} deg' if args.handheld else ''}, "
          f"{'onnx' if args.segmenter == 'onnx' else f'noisy painter ({args.noise_bias})' if args.noise else 'clean painter'} masks, "
          f"seed {args.seed}, options "
          f"{args.track_options or 'default'}; load average {os.getloadavg()[0]:.2f}")
    if args.segmenter == "onnx":
        print(f"onnx masks against the painter's (clean): IoU mean {np.mean(iou):.3f} (min {np.min(iou):.3f}), area "
              f"ratio median {np.median(area):.3f}")
    print_timing(summary, frames)
    tracked = [line["frame"] for line in frames if line["skipped"] is None]
    e3, e2 = errors([frames[i]["T_cam_root"] for i in tracked], tracked)
    print(f"tracked, end effector: 3D median {np.median(e3):.1f} mm (mean {e3.mean():.1f}, max {e3.max():.1f}), "
          f"2D median {np.median(e2):.2f} px (mean {e2.mean():.2f}, max {e2.max():.2f})")
    # under --noise even frames are eroded and odd ones dilated: every other pick is moved on by a frame, so an even
    # step samples both kinds (until session 49 it sampled eroded frames only)
    alternate = args.noise and args.noise_bias == "alternate"
    picked = [i + (j % 2 if alternate and args.single_every % 2 == 0 else 0)
              for j, i in enumerate(range(0, n, args.single_every))]
    picked = [i for i in picked if i in tracked]
    single = [estimate_pose(masks[i], fit_model, torch.from_numpy(joints[i]), camera, PoseFitConfig()).T_cam_root
              for i in picked]
    s3, s2 = errors(single, picked)
    t3, t2 = errors([frames[i]["T_cam_root"] for i in picked], picked)
    print(f"frames {picked}: tracked 3D {np.round(t3, 1).tolist()} mm (median {np.median(t3):.1f}), "
          f"independent single-frame fits {np.round(s3, 1).tolist()} mm (median {np.median(s3):.1f}); "
          f"2D median tracked {np.median(t2):.2f} px, single {np.median(s2):.2f} px")
    if alternate:
        for name, parity in (("eroded", 0), ("dilated", 1)):
            kind = np.array([i % 2 == parity for i in picked])
            if kind.any():
                print(f"  {name} frames {np.array(picked)[kind].tolist()}: 3D median tracked {np.median(t3[kind]):.1f} "
                      f"mm, single-frame {np.median(s3[kind]):.1f} mm")
    smoothed = [line["frame"] for line in frames if line.get("smooth_T_cam_root") is not None]
    if smoothed:  # --smooth-window: each line's pose read off lines in time through the last tracked frames
        m3, m2 = errors([frames[i]["smooth_T_cam_root"] for i in smoothed], smoothed)
        at = [i for i in picked if i in smoothed]
        p3, p2 = errors([frames[i]["smooth_T_cam_root"] for i in at], at)
        print(f"smoothed, end effector: 3D median {np.median(m3):.1f} mm over all frames (max {m3.max():.1f}), 2D "
              f"median {np.median(m2):.2f} px; at the picked frames {np.round(p3, 1).tolist()} mm (median "
              f"{np.median(p3):.1f}; single-frame fits {np.median(s3):.1f}), 2D median {np.median(p2):.2f} px")
    if static:
        j3, j2 = errors([summary["T_cam_root"]] * n, list(range(n)))
        print(f"static camera ({len(summary['static_camera']['frames'])} frames, trimmed "
              f"{summary['static_camera']['trimmed']}, {summary['static_camera']['seconds']:.1f} s): end effector "
              f"3D median {np.median(j3):.1f} mm over all frames (max {j3.max():.1f}), 2D median "
              f"{np.median(j2):.2f} px; median single-frame fit {np.median(s3):.1f} mm, median tracked frame {np.median(e3):.1f} mm")
        running = [line["frame"] for line in frames if line.get("static_T_cam_root") is not None]
        if running:  # --static-running: each line's running estimate, from the frames tracked up to it
            r3, r2 = errors([frames[i]["static_T_cam_root"] for i in running], running)
            print(f"running static estimate (from frame {running[0]}, "
                  f"{summary['static_camera'].get('running_seconds', 0.0):.1f} s in all): 3D median {np.median(r3):.1f} "
                  f"mm over its frames (max {r3.max():.1f}), 2D median {np.median(r2):.2f} px")
            at = [i for i in picked if i in running]
            if at:
                p3, _ = errors([frames[i]["static_T_cam_root"] for i in at], at)
                s_at, _ = errors([single[picked.index(i)] for i in at], at)
                print(f"  at the picked frames {at}: {np.round(p3, 1).tolist()} mm (median {np.median(p3):.1f}; their "
                      f"single-frame fits {np.median(s_at):.1f})")


if __name__ == "__main__":
    main()
