"""``pipeline track shape``: a soft arm's shape in every frame of a video or an image sequence (``pipeline.track``).

Frames come from ``--video FILE`` (decoded one by one, never all in memory) or ``--frames 'GLOB'`` (sorted by
name); masks from the segmenter options (``--segmenter file --mask-pattern 'masks/{frame:05d}.png'`` reads a mask
per frame, numbered as the video's frames). ``--out TRAJ.jsonl`` gets one line per frame as soon as it is done
(flushed, so a stopped run keeps every finished frame) and a summary line last.
"""

from __future__ import annotations

import argparse

from pipeline.cli._segmenter_args import add_segmenter_arguments


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "track",
        help="video tracking: soft-arm shape per frame, warm-started from the previous frame",
        description="Track a robot through a video or an image sequence, one estimate per frame.",
    )
    kinds = parser.add_subparsers(dest="track_kind", metavar="<kind>", title="kinds", required=True)
    shape = kinds.add_parser(
        "shape",
        help="soft continuum arm: centreline and radii per frame",
        description="Fit the soft arm in the first frame from scratch, then every frame from the previous "
        "estimate (one start, few iterations); a frame whose loss jumps above --reinit-ratio times the running "
        "loss is fitted from scratch again. Frames that cannot be read or show no robot are reported as skipped. "
        "Results refer to the undistorted image.",
    )
    shape.add_argument("--camera", required=True, metavar="CAM.json", help="camera intrinsics file")
    source = shape.add_mutually_exclusive_group(required=True)
    source.add_argument("--video", metavar="FILE", help="video file (anything OpenCV's VideoCapture reads)")
    source.add_argument("--frames", metavar="GLOB", help="image files, e.g. 'frames/*.png' (sorted by name)")
    shape.add_argument("--start", type=int, default=0, metavar="N", help="first frame (default 0)")
    shape.add_argument("--stop", type=int, metavar="N", help="stop before this frame (default: the last)")
    shape.add_argument("--step", type=int, default=1, metavar="N", help="take every N-th frame (default 1)")
    shape.add_argument(
        "--fps", type=float, metavar="F",
        help="frame rate for time_s (default: the video's; none for --frames, time_s is then null)",
    )  # fmt: skip
    shape.add_argument("--length", required=True, type=float, metavar="M", help="arm length, metres")
    shape.add_argument("--base-radius", required=True, type=float, metavar="M", help="radius at the base, metres")
    shape.add_argument("--tip-radius", required=True, type=float, metavar="M", help="radius at the tip, metres")
    shape.add_argument(
        "--order", default="auto", metavar="N|auto",
        help="Bezier order of the first (and any re-initialised) frame's fit, or auto (default: orders 2 to 5, the "
        "best kept); later frames keep the order of the estimate they start from",
    )  # fmt: skip
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
    shape.add_argument("--starts", type=int, default=4, metavar="N", help="hypotheses of a full fit (default 4)")
    shape.add_argument("--seed", type=int, default=0, metavar="N", help="seed of the random starts (default 0)")
    shape.add_argument("--max-side", type=int, default=320, metavar="PX",
                       help="working resolution (longest side of the cropped mask, default 320)")
    shape.add_argument("--warm-iterations", type=int, default=30, metavar="N",
                       help="Adam iterations of a warm-started frame (default 30)")
    shape.add_argument("--warm-prefit-iterations", type=int, default=100, metavar="N",
                       help="pre-fit iterations (no rendering) of a warm-started frame (default 100)")
    shape.add_argument("--reinit-ratio", type=float, default=3.0, metavar="R",
                       help="fit a frame from scratch when its loss exceeds R times the running loss (default 3)")
    shape.add_argument("--out", metavar="TRAJ.jsonl", help="write one JSON line per frame and a summary line")
    shape.add_argument("--overlay-video", metavar="OUT.mp4", help="write the frames with the fitted outline")
    shape.add_argument("--quiet", action="store_true", help="no progress bar (there is none when stderr is not a terminal)")
    add_segmenter_arguments(shape, default="auto")
    shape.set_defaults(func=run_shape)


def run_shape(args: argparse.Namespace) -> int:
    import time

    from tqdm.auto import tqdm

    from pipeline.camera import check_image_matches_camera, load_camera
    from pipeline.cli._segmenter_args import segmenter_from_args
    from pipeline.cli.shape import _parse_order, _parse_pixel
    from pipeline.robots import ContinuumRobot
    from pipeline.shape_estimation import ShapeFitConfig
    from pipeline.track import ShapeTrackConfig, ShapeTracker

    camera = load_camera(args.camera)
    robot = ContinuumRobot(length_m=args.length, base_radius_m=args.base_radius, tip_radius_m=args.tip_radius)
    common = dict(seed=args.seed, keypoint_mode=args.keypoint_mode, keypoints=args.keypoints,
                  working_max_side=args.max_side)
    config = ShapeTrackConfig(
        full_fit=ShapeFitConfig(order=_parse_order(args.order), iterations=args.iterations, starts=args.starts, **common),
        warm_fit=ShapeFitConfig(iterations=args.warm_iterations, starts=1,
                                prefit_iterations=args.warm_prefit_iterations, **common),
        reinit_ratio=args.reinit_ratio,
    )
    base_pixel = _parse_pixel(args.base_pixel, "--base-pixel") if args.base_pixel is not None else None
    segmenter = segmenter_from_args(args)
    source = _FrameSource(args)
    tracker = ShapeTracker(robot, camera, config, base_pixel=base_pixel)
    stages = {"decode": 0.0, "segment": 0.0, "fit": 0.0, "write": 0.0}
    out = open(args.out, "w", encoding="utf-8") if args.out is not None else None
    overlay = None
    frames = 0
    t_start = time.perf_counter()
    try:
        bar = tqdm(total=source.count, unit="frame", desc="track shape", disable=True if args.quiet else None)
        with bar:
            for index, time_s, image, decode_seconds, error in source.frames():
                stages["decode"] += decode_seconds
                frames += 1
                if error is not None:
                    tracked = tracker.skip(reason=error, frame=index, time_s=time_s)
                else:
                    check_image_matches_camera(image.shape[:2], camera)
                    t = time.perf_counter()
                    mask = segmenter(image, frame_index=index)
                    stages["segment"] += time.perf_counter() - t
                    tracked = tracker.step(mask, frame=index, time_s=time_s)
                    stages["fit"] += tracked.seconds
                t = time.perf_counter()
                if out is not None:
                    _write_line(out, tracked.to_dict())
                if args.overlay_video is not None and image is not None:
                    overlay = overlay or _VideoWriter(args.overlay_video, source.fps or 10.0, image.shape[:2])
                    overlay.write(_overlay(image, tracked, camera, robot))
                stages["write"] += time.perf_counter() - t
                bar.update(1)
                bar.set_postfix_str(f"{frames / (time.perf_counter() - t_start):.2f} fps")
        if frames == 0:
            from pipeline.errors import ConfigError

            raise ConfigError(f"no frame to track: {source.describe()} gave none between --start {args.start} and "
                              f"--stop {args.stop}")
        seconds = time.perf_counter() - t_start
        summary = {"summary": True, "frames": frames, "skipped": tracker.skipped,
                   "reinitialisations": tracker.reinitialisations, "fps": frames / seconds, "seconds": seconds,
                   **{f"{name}_seconds": value for name, value in stages.items()}}
        if out is not None:
            _write_line(out, summary)
    finally:
        source.close()
        if out is not None:
            out.close()
        if overlay is not None:
            overlay.close()
    print(f"track shape: {frames} frames ({tracker.skipped} skipped, {tracker.reinitialisations} re-initialised) at "
          f"{summary['fps']:.2f} frames/s; decode {stages['decode']:.2f} s, segment {stages['segment']:.2f} s, "
          f"fit {stages['fit']:.2f} s, write {stages['write']:.2f} s" + (f"; wrote {args.out}" if args.out else ""))
    return 0


def _write_line(out, record: dict) -> None:
    from pipeline.io import json_line

    out.write(json_line(record) + "\n")
    out.flush()


def _overlay(image, tracked, camera, robot):
    import cv2

    from pipeline.camera import undistort_image
    from pipeline.shape_estimation import draw_shape_overlay

    background = undistort_image(image, camera)[0]
    if tracked.result is None:
        out = background.copy()
        cv2.putText(out, f"frame {tracked.frame}: skipped", (10, 25), cv2.FONT_HERSHEY_SIMPLEX, 0.7, (0, 0, 255), 2)
        return out
    return draw_shape_overlay(background, tracked.result, robot)


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
        self.capture = None
        self.files: list[str] = []
        self.fps = args.fps
        if args.video is not None:
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
        end = total if self.stop is None else min(total, self.stop)
        self.count = max(0, (end - self.start + self.step - 1) // self.step) if total > 0 else None

    def describe(self) -> str:
        return f"--video {self.video}" if self.video is not None else f"--frames ({len(self.files)} files)"

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
        index = 0
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
            yield index, self._time(index), image, time.perf_counter() - t, None
            index += 1

    def _time(self, index: int) -> float | None:
        return None if self.fps is None else index / self.fps

    def close(self) -> None:
        if self.capture is not None:
            self.capture.release()
