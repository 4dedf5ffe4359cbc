"""``pipeline pose``: camera-to-robot pose of a URDF manipulator from one mask (or image) and its joint readings."""

from __future__ import annotations

import argparse

from pipeline.cli._segmenter_args import add_segmenter_arguments


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "pose",
        help="estimate T_cam_root of a manipulator from one mask or image and its joint readings",
        description="Fit the pose of the robot's root link in the camera frame (T_cam_root) so that the robot, "
        "rendered from its URDF at the given joint readings, covers the mask. Writes a JSON result (to --out, "
        "else to stdout) and optionally an overlay and a loss-history plot. Joint values are radians (revolute) "
        "or metres (prismatic).",
    )
    parser.add_argument("--camera", required=True, metavar="CAM.json", help="camera intrinsics file")
    add_robot_arguments(parser)
    add_joint_arguments(parser)
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--mask", metavar="MASK.png", help="robot mask (grey > 127 is robot), the camera's size")
    source.add_argument("--image", metavar="IMG", help="colour image, segmented with the segmenter options below")
    add_fit_arguments(parser)
    parser.add_argument("--out", metavar="RESULT.json", help="write the result here (default: print it)")
    parser.add_argument("--overlay", metavar="OVERLAY.png", help="write the fitted outline and link frames")
    parser.add_argument("--history", metavar="HISTORY.png", help="write the loss history of every start")
    add_segmenter_arguments(parser)
    parser.set_defaults(func=run)


def add_robot_arguments(parser: argparse.ArgumentParser) -> None:
    """The robot description options (shared with ``track pose``); :func:`load_model` reads them."""
    parser.add_argument(
        "--robot", "--urdf", dest="robot", required=True, metavar="FILE",
        help="robot description: URDF (plain, no xacro), MJCF (.xml) or SDF; the format is read from the file "
        "(--urdf is an alias)",
    )  # fmt: skip
    parser.add_argument(
        "--root", metavar="LINK", help="link (MJCF: body) whose pose in the camera is estimated (default: the "
        "description's top link, the one no joint has as its child; MJCF: world)"
    )
    parser.add_argument("--tip", metavar="LINK", help="render only the chain root..tip and the subtree below tip")
    parser.add_argument("--exclude", metavar="LINK,...", help="links not to render (comma-separated)")
    parser.add_argument(
        "--primitive", choices=("auto", "collision", "box", "cylinder", "hull", "cad"), default="auto",
        help="link geometry: auto (default: the convex hull of a link's visual meshes where it has some, else its "
        "collision geometry), the description's collision primitives, one box or cylinder per link, the convex hull "
        "of each link's geometry, or the CAD visual meshes",
    )  # fmt: skip
    parser.add_argument(
        "--cad-faces", type=int, default=3000, metavar="N",
        help="--primitive cad: decimate each link's mesh to at most N faces (default 3000; cached on disk)",
    )  # fmt: skip
    parser.add_argument(
        "--cad-faces-per-cm2", type=float, default=1.0, metavar="D",
        help="--primitive cad: and to D faces per cm^2 of the link's surface, at least 100 (default 1; 0: N faces "
        "for every link)",
    )  # fmt: skip
    parser.add_argument(
        "--cad-tolerance-mm", type=float, default=None, metavar="MM",
        help="--primitive cad: a link's face budget doubled until its silhouettes stray at most MM millimetres from "
        "its full mesh's (default: the loader's; 0: the budget alone). Either way the fit ends with a short polish "
        "drawn with the meshes within 1 mm (see --outline-polish)",
    )  # fmt: skip
    parser.add_argument(
        "--hull-faces", type=int, default=300, metavar="N",
        help="--primitive hull: decimate each link's convex hull to at most N faces (default 300)",
    )  # fmt: skip
    parser.add_argument(
        "--primitive-size", choices=("bbox", "volume"), default="bbox",
        help="box/cylinder links: bounding the link's geometry (default), or scaled to its volume (closer depth "
        "when the description has the link's meshes; docs/accuracy.md)",
    )  # fmt: skip
    parser.add_argument(
        "--package", action="append", default=[], metavar="NAME=DIR", help="folder of a package:// name (repeat)"
    )


def add_joint_arguments(parser: argparse.ArgumentParser, *, csv: bool = False) -> None:
    """One of ``--joints`` / ``--joints-file`` (and ``--joints-csv`` with ``csv``), and ``--zero-missing``."""
    joints = parser.add_mutually_exclusive_group(required=True)
    joints.add_argument("--joints", metavar="NAME=VALUE,...", help="joint readings, e.g. joint1=0.3,joint2=-1.2")
    joints.add_argument("--joints-file", metavar="JOINTS.json", help='joint readings as a JSON object {"name": value}')
    if csv:
        joints.add_argument(
            "--joints-csv", metavar="FILE",
            help="per-frame joint readings: a header row with frame, optionally time_s, and joint names; one row per "
            "frame",
        )  # fmt: skip
        parser.add_argument(
            "--interpolate-joints", action="store_true",
            help="with --joints-csv: a frame without a row is interpolated from the rows before and after it (by "
            "time_s where the file and the video have times, else by frame index) instead of being an error",
        )  # fmt: skip
    parser.add_argument("--zero-missing", action="store_true", help="set joints without a reading to 0 (warning)")


def add_fit_arguments(parser: argparse.ArgumentParser) -> None:
    """The single-frame fit options (shared with ``track pose``, for its full fits); :func:`fit_config` reads them."""
    parser.add_argument("--iterations", type=int, default=None, metavar="N",
                        help="Adam steps in all (default: 500 with --primitive cad, 300 with any other geometry)")
    parser.add_argument(
        "--starts", type=int, default=32, metavar="N", help="hypotheses in the first (coarsest) stage (default 32)"
    )
    parser.add_argument("--seed", type=int, default=0, metavar="N", help="seed of the random initialisation")
    parser.add_argument(
        "--hull-points", type=int, default=48, metavar="N",
        help="vertices per link of the hulls that score the starts and draw the coarse stages (grown to the link "
             "hull's volume; default 48; 16 is 0.65-0.8x the time of a fit without CAD, with more turned fits on "
             "the project's reported views: docs/any-manipulator.md)",
    )  # fmt: skip
    parser.add_argument(
        "--retries", type=int, default=1, metavar="N",
        help="fit again (next seed) while the loss stays above 0.15, a wrong basin; at most N times (default 1); a "
             "retry stops after its second stage unless its loss there is 10 %% below the first fit's. Links drawn as "
             "hulls (the default where the description has visual meshes) ask the visual meshes instead: see "
             "--retry-outline-loss",
    )  # fmt: skip
    parser.add_argument(
        "--retry-outline-loss", type=float, default=0.08, metavar="L",
        help="with links drawn as hulls, retry when the visual meshes' loss at the fit's pose is above L (a hull "
             "is wider than its link, so the hulls' own loss stays high at a clean mask's right pose; default 0.08; "
             "0: by the hulls' own loss against 0.15; docs/any-manipulator.md)",
    )  # fmt: skip
    parser.add_argument(
        "--outline-polish", action=argparse.BooleanOptionalAction, default=None,
        help="with links drawn as hulls, polish the answer once more drawn with the visual meshes (the polish of a "
             "--primitive cad fit): about CAD's millimetres and depth for 0.5-3 s more (default: when a retry ran, "
             "i.e. the mask was left poorly explained, as a segmenter's often is); with --primitive cad, a few "
             "steps drawn with the meshes within 1 mm of their outline, where the face budget leaves a link "
             "farther off (default: always; docs/any-manipulator.md)",
    )  # fmt: skip
    parser.add_argument(
        "--flip-candidates", type=int, default=0, metavar="N",
        help="also score the 180-degree turns of the N best initial candidates about the mask's principal axes and "
        "the optical axis (mirror images of a near-symmetric silhouette; default 0: off)",
    )  # fmt: skip
    parser.add_argument(
        "--boundary-offset", action=argparse.BooleanOptionalAction, default=False,
        help="estimate how far the mask's outline lies outside the robot's (a segmenter's dilation or erosion) and "
        "fit the mask's level set that far inside (default off; docs/any-manipulator.md)",
    )  # fmt: skip
    parser.add_argument(
        "--polish-boundary-offset", action=argparse.BooleanOptionalAction, default=None,
        help="fit that offset in the polish as a seventh unknown beside the pose, so the links' lengths tell it from "
        "the depth (default: on with --primitive cad, off with any other geometry, whose outline is not the "
        "robot's; docs/any-manipulator.md)",
    )  # fmt: skip
    parser.add_argument(
        "--boundary-refits", type=int, default=1, metavar="N",
        help="when the polish finds the mask's outline 1 px or more outside the robot's (--polish-boundary-offset: "
        "with --primitive cad), fit again on the mask with that offset taken off, at most N times, and keep the lower "
        "loss: a biased outline leads the fit to another basin before the offset is found (default 1; 0: never; "
        "docs/any-manipulator.md)",
    )  # fmt: skip
    parser.add_argument(
        "--weight-hidden", type=float, default=1.0, metavar="W",
        help="weight of rendered pixels more than 6 px outside the mask, where an occluder or a segmenter's miss may "
        "hide the robot: 0.25 for masks with holes (a real segmenter's, an occluded arm); default 1, every pixel "
        "alike (docs/any-manipulator.md)",
    )  # fmt: skip
    parser.add_argument(
        "--retry-weight-hidden", type=float, default=0.25, metavar="W",
        help="the --weight-hidden of the retry, which runs when the first fit leaves the mask poorly explained "
        "(loss above 0.15: often a mask with holes); its fit is kept if its pose scores lower under W (default "
        "0.25; the same as --weight-hidden: a plain retry with the next seed; docs/any-manipulator.md)",
    )  # fmt: skip
    parser.add_argument(
        "--weight-appearance", type=float, default=0.0, metavar="W",
        help="weight of the appearance term (rendered area against the mask's; the paper's 1); default 0: with "
        "link geometry that is not exactly the robot's outline (primitives, decimated meshes, a segmenter's mask) "
        "the area pulls the depth (docs/any-manipulator.md)",
    )  # fmt: skip
    parser.add_argument(
        "--polish-newton-steps", type=int, default=15, metavar="N",
        help="Gauss-Newton steps of the polish of the best pose on the hard-silhouette loss (default 15; 0: none)",
    )  # fmt: skip
    parser.add_argument(
        "--polish-rounds", type=int, default=None, metavar="N",
        help="random-search rounds of the polish after the Gauss-Newton steps (default: 40 with --primitive cad, 10 "
        "with any other geometry; 0: none)",
    )  # fmt: skip
    parser.add_argument(
        "--polish-newton-patience", type=int, default=None, metavar="N",
        help="end the polish's Gauss-Newton steps after N in a row without a lower loss (default: 3 with "
        "--primitive cad, 0 with any other geometry; 0: run them all)",
    )  # fmt: skip
    parser.add_argument(
        "--polish-min-step-px", type=float, default=None, metavar="PX",
        help="end the polish's random search once its step has shrunk below PX pixels (default: 0.1 with "
        "--primitive cad, 0 with any other geometry; 0: run every round)",
    )  # fmt: skip
    parser.add_argument(
        "--lr-offsets", type=float, default=0.0, metavar="LR",
        help="learning rate of per-vertex offsets of the link geometry in metres (the paper's 1e-4; default 0: off, "
        "offsets trade depth for shape)",
    )  # fmt: skip
    parser.add_argument(
        "--working-max-side", type=int, default=640, metavar="N",
        help="longest side of the working resolution in pixels (default 640)",
    )  # fmt: skip


def load_model(args: argparse.Namespace):  # -> pipeline.robots.ManipulatorModel
    """The robot the options of :func:`add_robot_arguments` describe (once per process under ``batch``)."""
    from pipeline.cli._args import file_stamp, loaded_once
    from pipeline.robots.manipulator import load_robot

    options = dict(tip=args.tip, exclude=tuple(_names(args.exclude)), primitive=args.primitive,
                   primitive_size=args.primitive_size, package_map=_package_map(args.package),
                   cad_faces=args.cad_faces, hull_faces=args.hull_faces,
                   cad_faces_per_cm2=args.cad_faces_per_cm2 or None)  # fmt: skip
    if args.cad_tolerance_mm is not None:
        options["cad_tolerance_m"] = args.cad_tolerance_mm * 1e-3 or None
    key = ("robot", file_stamp(args.robot), args.root, tuple(sorted((k, str(v)) for k, v in options.items())))
    # a first load that decimates meshes takes a minute or two: a bar on a terminal, not in batch workers
    progress = getattr(args, "model_cache", None) is None and not getattr(args, "quiet", False)
    return loaded_once(args, key, lambda: load_robot(args.robot, args.root, progress=progress, **options))


def fit_config(args: argparse.Namespace):  # -> pipeline.pose_estimation.PoseFitConfig
    """The fit settings the options of :func:`add_fit_arguments` describe."""
    import dataclasses

    from pipeline.pose_estimation import PoseFitConfig

    return dataclasses.replace(PoseFitConfig(), iterations=args.iterations, starts=args.starts, seed=args.seed,
                               working_max_side=args.working_max_side, lr_offsets=args.lr_offsets,
                               hull_points=args.hull_points,
                               retries=args.retries, polish_newton_steps=args.polish_newton_steps,
                               polish_rounds=args.polish_rounds, flip_candidates=args.flip_candidates,
                               polish_newton_patience=args.polish_newton_patience,
                               polish_min_step_px=args.polish_min_step_px,
                               fit_boundary_offset=args.boundary_offset,
                               polish_boundary_offset=args.polish_boundary_offset,
                               boundary_refits=args.boundary_refits,
                               weight_appearance=args.weight_appearance, weight_hidden=args.weight_hidden,
                               retry_weight_hidden=args.retry_weight_hidden,
                               retry_outline_loss=args.retry_outline_loss or None,
                               outline_polish=args.outline_polish)


def constant_joint_readings(args: argparse.Namespace) -> dict[str, float]:
    """The readings of ``--joints`` or ``--joints-file``."""
    return _joint_readings(args.joints) if args.joints is not None else _joints_file(args.joints_file)


def run(args: argparse.Namespace) -> int:
    import json
    import sys

    from pipeline.camera import check_image_matches_camera, load_camera
    from pipeline.io import read_image, read_mask, write_image, write_json
    from pipeline.pose_estimation import draw_pose_overlay, estimate_pose_from_readings, pose_result_json
    from pipeline.viz import gray_to_bgr, plot_history

    camera = load_camera(args.camera)
    model = load_model(args)
    readings = constant_joint_readings(args)
    config = fit_config(args)
    image = None
    if args.mask is not None:
        mask = read_mask(args.mask)
    else:
        from pipeline.cli._segmenter_args import segment_image

        image = read_image(args.image)
        check_image_matches_camera(image.shape[:2], camera)
        mask = segment_image(args, image, args.image)
    check_image_matches_camera(mask.shape, camera)
    result = estimate_pose_from_readings(mask, model, readings, camera, config, zero_missing=args.zero_missing)
    output = pose_result_json(result, model, camera)
    if args.out is not None:
        write_json(args.out, output)
    if args.overlay is not None:
        write_image(args.overlay, draw_pose_overlay(gray_to_bgr(mask) if image is None else image, model, result,
                                                    camera))
    if args.history is not None:
        write_image(args.history, plot_history(result.history, title="pose loss", best_start=result.best_start))
    if args.out is None:
        json.dump(output, sys.stdout, indent=2)
        print()
    else:
        print(_summary_line(args.out, output))
    return 0


def _summary_line(path: str, output: dict) -> str:
    """The one line ``pose --out`` prints for its result (``pose_result_json``'s dict): the translation, the depth's
    error bar, the loss and time, and where the JSON says so, that another pose explains the mask about as well."""
    t = output["T_cam_root"]
    std, dropped = output["depth_std_m"], output["mask_dropped_fraction"]
    line = (f"{path}: T_cam_root t = ({t[0][3]:.4f}, {t[1][3]:.4f}, {t[2][3]:.4f}) m"
            + (f" (depth +- {1000 * std:.0f} mm)" if std is not None else "")
            + f", loss {output['loss']:.4g}, {output['iterations']} iterations, {output['seconds']:.1f} s"
            + (f", {100 * dropped:.1f}% of the mask unexplained" if dropped else ""))
    if output["ambiguous"]:
        runner = output["runner_up"]
        line += (f"; ambiguous: a pose {runner['rotation_deg']:.0f} degrees away explains the mask at "
                 f"{runner['loss_ratio']:.2f}x the loss (runner_up in the JSON; check the overlay)")
    return line


def _names(text: str | None) -> tuple[str, ...]:
    return tuple(n.strip() for n in text.split(",") if n.strip()) if text else ()


def _joint_readings(text: str) -> dict[str, float]:
    """``"a=0.1,b=-2"`` -> ``{"a": 0.1, "b": -2.0}``."""
    from pipeline.errors import ConfigError

    readings: dict[str, float] = {}
    for item in text.split(","):
        name, sep, value = item.partition("=")
        name = name.strip()
        try:
            number = float(value)
        except ValueError:
            number = None
        if not sep or not name or number is None:
            raise ConfigError(f"--joints: expected NAME=VALUE,... with numbers, got {item!r} in {text!r}")
        if name in readings:
            raise ConfigError(f"--joints: joint {name!r} is given twice")
        readings[name] = number
    return readings


def _joints_file(path: str) -> dict[str, float]:
    """A JSON object ``{"name": value, ...}`` of joint readings."""
    import json
    from pathlib import Path

    from pipeline.errors import AssetError, ConfigError

    try:
        data = json.loads(Path(path).read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise AssetError(f"joints file not found: {path}") from None
    except (OSError, UnicodeDecodeError) as e:
        raise AssetError(f"cannot read joints file {path}: {e}") from None
    except json.JSONDecodeError as e:
        raise ConfigError(f"{path}: not valid JSON ({e.msg} at line {e.lineno})") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a JSON object of joint readings {{\"name\": value}}, got "
                          f"{type(data).__name__}")
    return data


def _package_map(items: list[str]) -> dict[str, str]:
    from pipeline.errors import ConfigError

    packages = {}
    for item in items:
        name, sep, folder = item.partition("=")
        if not sep or not name.strip() or not folder.strip():
            raise ConfigError(f"--package: expected NAME=DIR, got {item!r}")
        packages[name.strip()] = folder.strip()
    return packages
