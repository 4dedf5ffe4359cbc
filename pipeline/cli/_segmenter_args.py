"""Segmenter options shared by every command that takes ``--image`` (``pose``, ``shape``, ``track``, ``segment``).

Usage in a command module::

    def add_parser(subparsers):
        parser = subparsers.add_parser(...)
        parser.add_argument("--image", ...)
        add_segmenter_arguments(parser)            # or add_segmenter_arguments(parser, default="color")

    def run(args):
        segmenter = segmenter_from_args(args)      # raises ConfigError / AssetError on bad options
        mask = segmenter(image, frame_index=0)

Options given for another kind than ``--segmenter`` names are an error (they would be silently ignored).
This module imports no heavy library at import time, so ``--help`` stays fast.
"""

from __future__ import annotations

import argparse

from pipeline.errors import ConfigError

SEGMENTER_CHOICES = ("auto", "color", "onnx", "file")

# option destination -> (flag, the segmenter kinds it belongs to)
_KIND_OPTIONS = {
    "hsv_preset": ("--hsv-preset", ("color",)),
    "hsv_lower": ("--hsv-lower", ("color",)),
    "hsv_upper": ("--hsv-upper", ("color",)),
    "open_px": ("--open-px", ("color",)),
    "close_px": ("--close-px", ("color",)),
    "all_components": ("--all-components", ("color", "onnx", "auto")),
    "onnx_model": ("--onnx-model", ("onnx", "auto")),
    "onnx_device": ("--onnx-device", ("onnx", "auto")),
    "onnx_threads": ("--onnx-threads", ("onnx", "auto")),
    "onnx_max_side": ("--onnx-max-side", ("onnx", "auto")),
    "refine_band_px": ("--refine-band-px", ("auto",)),
    "refine_iterations": ("--refine-iterations", ("auto",)),
    "mask_pattern": ("--mask-pattern", ("file",)),
}


def add_segmenter_arguments(parser: argparse.ArgumentParser, *, default: str = "onnx") -> None:
    """Add the segmenter options to ``parser``; ``default`` is the kind used when ``--segmenter`` is not given."""
    if default not in SEGMENTER_CHOICES:
        raise ConfigError(f"default: expected one of {', '.join(SEGMENTER_CHOICES)}, got {default!r}")
    group = parser.add_argument_group(
        "segmenter (with --image)",
        "How the robot mask is made from the image. auto: the onnx network's mask refined by GrabCut with colour "
        "models estimated from the image (any arm colour, nothing to configure). colour: HSV thresholds (OpenCV "
        "units: H 0-179, S and V 0-255; a hue range with lower > upper wraps around red), opening, closing, "
        "largest component. onnx: a "
        "segmentation network (models/segmenters/NAME/model.onnx + meta.json). file: masks made elsewhere.",
    )
    group.add_argument(
        "--segmenter", choices=SEGMENTER_CHOICES, default=default, help=f"segmenter kind (default: {default})"
    )
    group.add_argument(
        "--hsv-preset", metavar="NAME",
        help="color: a named HSV range (default soft_arm, the bundled soft-arm examples' colour; also red, "
        "orange, yellow, green, blue)",
    )  # fmt: skip
    group.add_argument("--hsv-lower", metavar="H,S,V", help="color: lower HSV bounds (with --hsv-upper)")
    group.add_argument("--hsv-upper", metavar="H,S,V", help="color: upper HSV bounds (with --hsv-lower)")
    group.add_argument("--open-px", type=int, metavar="N", help="color: opening diameter in pixels (default 3)")
    group.add_argument("--close-px", type=int, metavar="N", help="color: closing diameter in pixels (default 5)")
    group.add_argument(
        "--all-components", action="store_true", default=None,
        help="color, onnx, auto: keep every connected component of the mask (default: only the largest; shape and "
        "track shape always keep every one and fit the arm's)",
    )  # fmt: skip
    group.add_argument(
        "--refine-band-px", type=int, metavar="N",
        help="auto: how far (pixels) the refinement may move the network mask's rim either way (default 6)",
    )  # fmt: skip
    group.add_argument(
        "--refine-iterations", type=int, metavar="N",
        help="auto: GrabCut iterations of the refinement (default 3; 5 for a first mask far from the arm's rim, "
             "docs/segmenters.md)",
    )  # fmt: skip
    group.add_argument(
        "--onnx-model", metavar="NAME_OR_PATH",
        help="onnx, auto: model name under models/segmenters/, a model folder or its model.onnx (default "
        "robot_deeplab)",
    )  # fmt: skip
    group.add_argument(
        "--onnx-device", choices=("auto", "cpu", "cuda"),
        help="onnx, auto: execution provider (default auto: CUDA when onnxruntime has it, else CPU)",
    )  # fmt: skip
    group.add_argument(
        "--onnx-threads", type=int, metavar="N", help="onnx, auto: CPU threads (default 0: onnxruntime's choice)"
    )
    group.add_argument(
        "--onnx-max-side", type=int, metavar="N",
        help="onnx, auto: shrink a larger image to this longer side before the network (default: the model's "
        "meta.json, 960 for robot_deeplab, trained on 640x480 renders; 0: never shrink)",
    )  # fmt: skip
    group.add_argument(
        "--mask-pattern", metavar="PATTERN",
        help="file: mask path, or a per-frame pattern such as masks/{frame:05d}.png (frame index from 0)",
    )  # fmt: skip


def segmenter_config_from_args(args: argparse.Namespace):  # -> pipeline.segment.SegmenterConfig
    """The segmenter config the parsed options describe (picklable; build it with ``make_segmenter``).

    Raises:
        ConfigError: an option of another segmenter kind, half an HSV range, a preset together with explicit
            bounds, an unknown preset, or ``--segmenter file`` without ``--mask-pattern``.
    """
    from pipeline.segment import (
        AutoSegmenterConfig,
        ColorSegmenterConfig,
        FileSegmenterConfig,
        OnnxSegmenterConfig,
        color_preset,
        parse_hsv,
    )

    kind = args.segmenter
    for dest, (flag, owners) in _KIND_OPTIONS.items():
        if kind not in owners and getattr(args, dest, None) is not None:
            raise ConfigError(f"{flag} is an option of --segmenter {' and '.join(owners)}, but --segmenter is {kind}")
    if kind == "color":
        options = {}
        if args.open_px is not None:
            options["open_px"] = args.open_px
        if args.close_px is not None:
            options["close_px"] = args.close_px
        if args.all_components:
            options["largest_component"] = False
        if (args.hsv_lower is None) != (args.hsv_upper is None):
            raise ConfigError("--hsv-lower and --hsv-upper go together: give both (or neither, for a preset)")
        if args.hsv_lower is not None:
            if args.hsv_preset is not None:
                raise ConfigError("give either --hsv-preset or --hsv-lower/--hsv-upper, not both")
            lower, upper = parse_hsv(args.hsv_lower, "--hsv-lower"), parse_hsv(args.hsv_upper, "--hsv-upper")
            return ColorSegmenterConfig(hsv_lower=lower, hsv_upper=upper, **options)
        return color_preset(args.hsv_preset if args.hsv_preset is not None else "soft_arm", **options)
    if kind in ("onnx", "auto"):
        options = {}
        if args.onnx_model is not None:
            options["model"] = args.onnx_model
        if args.onnx_device is not None:
            options["device"] = args.onnx_device
        if args.onnx_threads is not None:
            options["num_threads"] = args.onnx_threads
        if args.onnx_max_side is not None:
            options["max_side"] = args.onnx_max_side
        if args.all_components:
            options["largest_component"] = False
        if kind == "onnx":
            return OnnxSegmenterConfig(**options)
        if args.refine_band_px is not None:
            options["band_px"] = args.refine_band_px
        if args.refine_iterations is not None:
            options["iterations"] = args.refine_iterations
        return AutoSegmenterConfig(**options)
    if args.mask_pattern is None:
        raise ConfigError("--segmenter file needs --mask-pattern (a mask path or a pattern like masks/{frame:05d}.png)")
    return FileSegmenterConfig(pattern=args.mask_pattern)


def segmenter_from_args(args: argparse.Namespace):  # -> pipeline.segment.Segmenter
    """The segmenter the parsed options describe; see :func:`segmenter_config_from_args`."""
    from pipeline.cli._args import loaded_once
    from pipeline.segment import make_segmenter

    config = segmenter_config_from_args(args)
    return loaded_once(args, ("segmenter", config), lambda: make_segmenter(config))


#: What to try when a segmenter finds nothing, per ``--segmenter`` kind.
_INSTEAD = {
    "auto": "try --segmenter color with --hsv-lower/--hsv-upper around your robot's colour, --segmenter onnx "
            "--onnx-model with a network trained on your robot, or a mask of your own (--mask)",
    "onnx": "try --segmenter auto, --segmenter color with --hsv-lower/--hsv-upper, or a mask of your own (--mask)",
    "color": "try --hsv-lower/--hsv-upper around your robot's colour (python -m pipeline segment --image IMG "
             "--overlay OUT.png shows what they keep), --segmenter auto, or a mask of your own (--mask)",
    "file": "check the mask file that --mask-pattern names for this image",
}


def segment_image(args: argparse.Namespace, image, path: str):  # (H, W, 3) uint8 -> (H, W) bool
    """``segmenter_from_args(args)(image)``; a mask without a robot pixel is an error that names the image, the
    segmenter and what to try instead (rather than the fit's later "mask is empty").

    Raises:
        ShapeError: the segmenter found no robot pixel in ``image`` (read from ``path``).
    """
    from pipeline.errors import ShapeError

    mask = segmenter_from_args(args)(image, frame_index=0)
    if not mask.any():
        kind = args.segmenter
        raise ShapeError(f"--image {path}: the {kind} segmenter found no robot pixel (is the robot in view?); "
                         f"{_INSTEAD.get(kind, 'try another --segmenter')}")
    return mask
