"""``pipeline segment``: run a segmenter alone on one image and write its mask (and an overlay)."""

from __future__ import annotations

import argparse

from pipeline.cli._segmenter_args import add_segmenter_arguments


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "segment",
        help="segment one image into a robot mask (to inspect a segmenter)",
        description="Run a segmenter on IMG and write the robot mask as a uint8 0/255 PNG; print one summary line.",
    )
    parser.add_argument("--image", required=True, metavar="IMG", help="colour image")
    parser.add_argument("--out", required=True, metavar="MASK.png", help="write the mask here")
    parser.add_argument("--overlay", metavar="OVERLAY.png", help="write the image with the mask tinted green")
    parser.add_argument(
        "--frame", type=int, default=0, metavar="N", help="frame index given to the segmenter (file patterns)"
    )
    add_segmenter_arguments(parser)
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import logging
    import time

    from pipeline.cli._segmenter_args import segmenter_from_args
    from pipeline.errors import ConfigError
    from pipeline.io import read_image, write_image, write_mask
    from pipeline.segment import mask_overlay

    if args.frame < 0:
        raise ConfigError(f"--frame: expected an int >= 0, got {args.frame}")
    image = read_image(args.image)
    segmenter = segmenter_from_args(args)
    start = time.perf_counter()
    mask = segmenter(image, frame_index=args.frame)
    ms = 1000.0 * (time.perf_counter() - start)
    if not mask.any():
        logging.getLogger(__name__).warning("the mask of %s is empty: no robot found", args.image)
    write_mask(args.out, mask)
    if args.overlay is not None:
        write_image(args.overlay, mask_overlay(image, mask))
    H, W = mask.shape
    print(
        f"{args.out}: {int(mask.sum())} robot pixels ({100.0 * mask.mean():.2f}% of {W}x{H}), "
        f"segmenter {args.segmenter}, {ms:.1f} ms"
    )
    return 0
