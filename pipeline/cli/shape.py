"""``pipeline shape``: the shape of a soft continuum arm from one image or mask (``reconstruct_shape``)."""

from __future__ import annotations

import argparse

from pipeline.cli._args import add_rim_offset_argument
from pipeline.cli._segmenter_args import add_segmenter_arguments


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "shape",
        help="soft continuum arm: centreline and radii from one image or mask",
        description="Fit a tapered tube around a Bezier centreline to the robot mask (from --mask, or segmented "
        "from --image) and write the control points, radii and centreline (camera frame, metres) as JSON. "
        "Results refer to the undistorted image (the mask is undistorted with the camera's coefficients). Where "
        "the mask has several large components (e.g. clutter the segmenter took for the robot), the one a tube of "
        "the given length and radii explains best is fitted, not the largest (JSON arm_candidates), and the pieces "
        "of an arm cut by something in front of it are joined; the segmenter keeps every component for it.",
    )
    parser.add_argument("--camera", required=True, metavar="CAM.json", help="camera intrinsics file")
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--mask", metavar="MASK.png", help="robot mask (grey > 127 is robot)")
    source.add_argument("--image", metavar="IMG", help="colour image, segmented with the segmenter options")
    parser.add_argument("--length", required=True, type=float, metavar="M", help="arm length, metres")
    parser.add_argument("--base-radius", required=True, type=float, metavar="M", help="radius at the base, metres")
    parser.add_argument("--tip-radius", required=True, type=float, metavar="M", help="radius at the tip, metres")
    parser.add_argument(
        "--order", default="auto", metavar="N|auto",
        help="Bezier order of the centreline, or auto (default): fit orders 2 to 5 in turn and keep the best after "
        "a penalty per extra control point (single bends keep 2; S shapes get more)",
    )  # fmt: skip
    add_model_arguments(parser, auto=True)
    parser.add_argument(
        "--pcc-start", choices=("bezier", "hypotheses"), default=None,
        help="pcc: refine the Bezier fit's answer (default; --order's search runs first; auto: this only) or race "
        "the mask's hypotheses as arcs (the PCC fit before 2026-11-29, farther from the truth on most arms)",
    )  # fmt: skip
    parser.add_argument(
        "--keypoint-mode", choices=("mask", "endpoint", "keypoints"), default="keypoints",
        help="loss: mask only, mask + the tip, or mask + --keypoints points along the arm (default keypoints)",
    )  # fmt: skip
    parser.add_argument("--keypoints", type=int, default=4, metavar="K", help="keypoints along the arm (default 4)")
    parser.add_argument(
        "--base-pixel", metavar="U,V",
        help="pixel of the arm's base (default: the skeleton end nearer the image border; when the arm's widths say "
        "the other end is the thicker, both ends are fitted and the lower loss kept)",
    )  # fmt: skip
    parser.add_argument("--iterations", type=int, default=200, metavar="N", help="Adam iterations (default 200)")
    parser.add_argument("--starts", type=int, default=8, metavar="N", help="hypotheses fitted together (default 8)")
    parser.add_argument("--seed", type=int, default=0, metavar="N", help="seed of the random starts (default 0)")
    parser.add_argument(
        "--max-side", type=int, default=480, metavar="PX",
        help="working resolution: the fit runs on the mask cropped around the robot and shrunk to this longest "
        "side (default 480; 320 is 10-20 %% faster and less accurate)",
    )  # fmt: skip
    add_rim_offset_argument(parser, auto="refit at 0, -2, -1, 1, 2 px after the fit and keep an offset that lowers "
                            "the loss clearly (about 1.5-1.8x the time)",
                            image="read from --image's colour edges across the mask's outline (the default with "
                            "--image, unless --segmenter file)")
    parser.add_argument("--out", metavar="RESULT.json", help="write the result here")
    parser.add_argument(
        "--overlay", metavar="OVERLAY.png",
        help="write the (undistorted) image or mask with the fitted outline, centreline and keypoints",
    )  # fmt: skip
    parser.add_argument("--history", metavar="HISTORY.png", help="write a plot of the loss per iteration")
    parser.add_argument("--progress", action="store_true", help="show a progress bar")
    add_segmenter_arguments(parser, default="auto")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from pipeline.camera import load_camera, undistort_image
    from pipeline.io import read_image, read_mask, write_image, write_json
    from pipeline.robots import ContinuumRobot
    from pipeline.shape_estimation import ShapeFitConfig, draw_shape_overlay, reconstruct_shape
    from pipeline.viz import gray_to_bgr, plot_history

    camera = load_camera(args.camera)
    robot = ContinuumRobot(length_m=args.length, base_radius_m=args.base_radius, tip_radius_m=args.tip_radius)
    lengths = model_section_lengths(args, "--pcc-start", auto=True)
    config = ShapeFitConfig(order=_parse_order(args.order), model=args.model, sections=args.sections,
                            section_lengths_m=lengths, pcc_start=args.pcc_start or "bezier", iterations=args.iterations,
                            starts=args.starts,
                            seed=args.seed,
                            keypoint_mode=args.keypoint_mode, keypoints=args.keypoints,
                            working_max_side=args.max_side, rim_offset_px=_rim_offset(args),
                            progress=args.progress)
    base_pixel = _parse_pixel(args.base_pixel, "--base-pixel") if args.base_pixel is not None else None
    if args.image is not None:
        from pipeline.camera import check_image_matches_camera
        from pipeline.cli._segmenter_args import segment_image

        image = read_image(args.image)
        check_image_matches_camera(image.shape[:2], camera)
        if args.segmenter in ("auto", "onnx", "color"):  # every component: the fit keeps the arm's (docs/segmenters.md)
            args.all_components = True
        mask = segment_image(args, image, args.image)
    else:
        mask = read_mask(args.mask)
        image = None
    result = reconstruct_shape(mask, robot, camera, config, base_pixel=base_pixel, image=image)

    if args.out is not None:
        content = result.to_dict()
        content["robot"] = {"length_m": robot.length_m, "base_radius_m": robot.base_radius_m,
                            "tip_radius_m": robot.tip_radius_m}
        content["input"] = {"image": args.image, "mask": args.mask}
        write_json(args.out, content)
    if args.overlay is not None:
        if image is not None:
            background = undistort_image(image, camera)[0]
        else:
            background = gray_to_bgr(undistort_image(mask, camera, is_mask=True)[0])
        write_image(args.overlay, draw_shape_overlay(background, result, robot))
    if args.history is not None:
        write_image(args.history, plot_history(result.history, title="shape loss", best_start=result.best_start))
    tip = result.centerline_cam_m[-1]
    model = f"pcc, {result.order} sections" if result.model == "pcc" else f"order {result.order}"
    print(f"shape: {model}, loss {result.loss:.4g} after {result.iterations} iterations in "
          f"{result.seconds:.2f} s; tip at "
          f"({tip[0]:.4f}, {tip[1]:.4f}, {tip[2]:.4f}) m" + (f"; wrote {args.out}" if args.out else ""))
    if result.model_losses:
        print(f"shape: model auto kept {result.model} (losses: "
              + ", ".join(f"{name} {loss:.4g}" for name, loss in result.model_losses.items()) + ")")
    if config.rim_offset_px == "image":
        print(f"shape: rim offset {result.rim_offset_px:+.2f} px read from the image (the mask's outline against its "
              f"colour edges)")
    if result.rim_offset_losses:
        print(f"shape: rim offset {result.rim_offset_px:+g} px kept (losses "
              + ", ".join(f"{offset:+g}: {loss:.4g}" for offset, loss in sorted(result.rim_offset_losses.items()))
              + ")")
    if result.other_end_loss is not None:
        print(f"shape: the image border and the widths named different base ends; both fitted, the other end's "
              f"loss {result.other_end_loss:.4g} (give --base-pixel to fix it)")
    return 0


def _rim_offset(args: argparse.Namespace) -> float | str:
    """``--rim-offset-px``, by default ``image`` with ``--image`` (a segmenter's rim read from the image) and 0
    with ``--mask`` or masks from files (taken as exact); ``image`` with ``--mask`` is refused."""
    from pipeline.errors import ConfigError

    if args.rim_offset_px is None:
        return "image" if args.image is not None and args.segmenter != "file" else 0.0
    if args.rim_offset_px == "image" and args.image is None:
        raise ConfigError("--rim-offset-px image: reads the rim from the colour image; give --image (with --mask, "
                          "give a number of pixels or auto)")
    return args.rim_offset_px


def _parse_pixel(text: str, option: str) -> tuple[float, float]:
    from pipeline.errors import ConfigError

    try:
        u, v = (float(part) for part in text.split(","))
    except ValueError:
        raise ConfigError(f"{option}: expected U,V (two numbers, pixels), got {text!r}") from None
    return (u, v)


def add_model_arguments(parser: argparse.ArgumentParser, *, auto: bool = False) -> None:
    """``--model``, ``--sections``, ``--section-lengths``: ``shape`` (``auto``: ``--model auto``, its default) and
    ``track shape`` (``bezier`` by default)."""
    models = "pcc, auto" if auto else "pcc"
    parser.add_argument(
        "--model", choices=("bezier", "pcc", "auto") if auto else ("bezier", "pcc"),
        default="auto" if auto else "bezier",
        help=("centreline model: auto (default): the Bezier curve of --order, then its refinement as --sections "
              "constant-curvature arcs, the lower loss kept (JSON: 'model' the one kept, 'model_losses' both); "
              "bezier: the Bezier curve alone; pcc: the arcs, kept whatever the loss" if auto else
              "centreline model: bezier (default, of --order) or pcc: piecewise constant curvature, --sections arcs, "
              "each with its curvature and bending plane")
        + " (pcc's JSON: control_points_cam_m are the section end points, 'pcc' the parameters)",
    )  # fmt: skip
    parser.add_argument("--sections", type=int, default=2, metavar="N",
                        help=f"{models}: number of constant-curvature sections (default 2)")
    parser.add_argument(
        "--section-lengths", metavar="L1,L2,...",
        help=f"{models}: the sections' lengths in metres, summing to --length (default: fitted, their sum held at "
        "--length)",
    )  # fmt: skip


def model_section_lengths(args: argparse.Namespace, *pcc_options: str, auto: bool = False) -> tuple[float, ...]:
    """The ``--section-lengths`` of ``add_model_arguments`` (``()``: fitted); a ``ConfigError`` when it, or one of
    ``pcc_options`` (more options of ``--model pcc`` and ``auto``, e.g. ``"--pcc-start"``), is given with
    ``--model bezier`` (``auto``: the parser offers ``--model auto``)."""
    from pipeline.errors import ConfigError

    for option in ("--section-lengths", *pcc_options):
        if args.model == "bezier" and getattr(args, option[2:].replace("-", "_")) is not None:
            raise ConfigError(f"{option} is an option of --model pcc{' and auto' if auto else ''}, but --model is "
                              f"bezier")
    return _parse_lengths(args.section_lengths) if args.section_lengths is not None else ()


def _parse_lengths(text: str) -> tuple[float, ...]:
    from pipeline.errors import ConfigError

    try:
        return tuple(float(part) for part in text.split(","))
    except ValueError:
        raise ConfigError(f"--section-lengths: expected L1,L2,... (numbers, metres), got {text!r}") from None


def _parse_order(text: str) -> int | str:
    from pipeline.errors import ConfigError

    if text == "auto":
        return text
    try:
        return int(text)
    except ValueError:
        raise ConfigError(f"--order: expected auto or an int >= 1 (the Bezier order), got {text!r}") from None
