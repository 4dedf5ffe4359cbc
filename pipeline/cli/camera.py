"""``pipeline camera``: validate a camera file, print it, and optionally write a resized copy."""

from __future__ import annotations

import argparse


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "camera",
        help="validate and print a camera file; optionally write a resized copy",
        description="Validate CAM.json and print it as JSON on stdout. With --resize or --max-side, print (and "
        "with --out, write) the camera for the resized image instead.",
    )
    parser.add_argument("--camera", required=True, metavar="CAM.json", help="camera intrinsics file")
    size = parser.add_mutually_exclusive_group()
    size.add_argument("--resize", metavar="WxH", help="new image size, e.g. 640x480")
    size.add_argument("--max-side", type=int, metavar="N", help="shrink so the longest side is at most N pixels")
    parser.add_argument("--out", metavar="CAM2.json", help="write the (resized) camera here")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from pipeline.camera import camera_to_json, load_camera, resize_camera, save_camera, working_camera
    from pipeline.cli._args import parse_size_wh

    camera = load_camera(args.camera)
    if args.resize is not None:
        camera = resize_camera(camera, parse_size_wh(args.resize, "--resize"))
    elif args.max_side is not None:
        camera = working_camera(camera, args.max_side)
    if args.out is not None:
        save_camera(camera, args.out)
    print(camera_to_json(camera))
    return 0
