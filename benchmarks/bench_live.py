"""Live soft-arm tracking: a synthetic video played as a camera, frames per second kept up with, latency, accuracy.

The moving arm of ``bench_track.py`` (``moving_bezier_arm``, 640x360 by default) is handed to
``pipeline.track.track_shape`` frame by frame at ``--fps`` frames per second of wall time, as a camera would hand
them (a frame the tracker is not ready for waits in the reader's queue; ``ShapeTrackConfig.live``: each fit takes
every frame that arrived meanwhile, at most ``--batch`` of them). The frames are the true masks, or with
``--segmenter auto`` the rendered images segmented by the command's default segmenter in the reader's thread.
Printed: the frames tracked per second after the first frame's full fit (the rate the camera is kept up with when
it is at least ``--fps``), each frame's latency (from the time the camera took it to its result: median and 90th
percentile, and the median over the last third of the frames, where the backlog of the first fit may be gone), the
batch sizes, the frames dropped (``--drop-late``: ``ShapeTrackConfig.drop_late``) and the mean 2D / 3D
centreline error of the tracked frames; then the same frames tracked one at a
time as fast as they come (``live=False``, ``batch_frames=1``: the reference, in the same run).

    python benchmarks/bench_live.py [--frames 100] [--fps 10] [--batch 8] [--order 2] [--seed 1] [--segmenter auto]
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from dataclasses import replace


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--frames", type=int, default=100)
    parser.add_argument("--fps", type=float, default=10.0, help="the camera's frame rate")
    parser.add_argument("--batch", type=int, default=8, help="the most frames one fit takes (batch_frames)")
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=360)
    parser.add_argument("--order", type=int, default=2)
    parser.add_argument("--period", type=float, default=50.0, help="frames per bending cycle")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--drop-late", action="store_true",
                        help="drop the oldest waiting frame when the tracker is a batch behind (drop_late)")
    parser.add_argument("--segmenter", choices=("file", "auto"), default="file",
                        help="file: the true masks (default); auto: the command's default segmenter on the images")
    args = parser.parse_args()

    import numpy as np

    from bench_track import moving_arm

    from pipeline.evaluate import centerline_errors
    from pipeline.robots import ContinuumRobot
    from pipeline.shape_estimation import ShapeFitConfig
    from pipeline.synth.soft_arm import render_tube_image
    from pipeline.track import ShapeTrackConfig, track_shape

    H, W = args.height, args.width
    camera, _, truths, _ = moving_arm(args)
    K = camera.K_array()
    radii = np.linspace(0.014, 0.006, 201)
    drawn = [render_tube_image(t, radii, K, (H, W), np.random.default_rng(0), supersample=4) for t in truths]
    segmenter = None
    frames = [mask for _, mask in drawn]
    if args.segmenter == "auto":
        from pipeline.segment import make_segmenter
        from pipeline.segment.refine import AutoSegmenterConfig

        segmenter = make_segmenter(AutoSegmenterConfig(largest_component=False))
        frames = [image for image, _ in drawn]
    robot = ContinuumRobot(length_m=0.2, base_radius_m=0.014, tip_radius_m=0.006)
    base = ShapeTrackConfig(full_fit=ShapeFitConfig(model="bezier", order=args.order))

    def camera_feed(arrivals: dict[int, float]):
        """The frames at the camera's times; a frame taken late (the reader's queue was full) counts from the time
        the camera took it, as if it had waited in the camera's own buffer."""
        start = time.perf_counter()
        for i, frame in enumerate(frames):
            arrivals[i] = start + i / args.fps
            delay = arrivals[i] - time.perf_counter()
            if delay > 0:
                time.sleep(delay)
            yield frame

    def run(config: ShapeTrackConfig, source) -> tuple[list, dict[int, float]]:
        done = {}
        tracked = []
        for item in track_shape(source, robot, camera, config, segmenter=segmenter):
            done[item.frame] = time.perf_counter()
            tracked.append(item)
        return tracked, done

    def errors(tracked) -> tuple[float, float]:
        e = np.array([[centerline_errors(t.result.centerline_cam_m, truths[t.frame], K)[k]
                       for k in ("mean_2d_px", "mean_3d_mm")] for t in tracked if t.result is not None])
        return float(e[:, 0].mean()), float(e[:, 1].mean())

    arrivals: dict[int, float] = {}
    live, done = run(replace(base, live=True, batch_frames=args.batch, drop_late=args.drop_late), camera_feed(arrivals))
    dropped = sum(t.skipped is not None for t in live)
    done = {t.frame: done[t.frame] for t in live if t.result is not None or t.frame == 0}
    first = done[0]
    later = [i for i in done if i > 0]
    rate = len(later) / (max(done[i] for i in later) - first)
    latency = sorted(done[i] - arrivals[i] for i in later)
    last = sorted(done[i] - arrivals[i] for i in later[-len(later) // 3:])  # the last third: caught up or not
    sizes: dict[int, int] = {}  # frames yielded within 5 ms of each other came from one batch
    group = 1
    for previous, i in zip(later, later[1:] + [None]):
        if i is not None and done[i] - done[previous] < 0.005:
            group += 1
            continue
        sizes[group] = sizes.get(group, 0) + 1
        group = 1
    print(f"{W}x{H}, {len(frames)} frames, order {args.order}, {args.segmenter} masks, camera {args.fps:g} "
          f"frames/s, batches of at most {args.batch}{', late frames dropped' if args.drop_late else ''}; load "
          f"average {os.getloadavg()[0]:.2f}")
    print(f"live: {rate:.2f} frames/s tracked after the first frame's full fit ({first - arrivals[0]:.2f} s), "
          f"{dropped} frames skipped (dropped); "
          f"latency median {statistics.median(latency):.2f} s, 90th percentile "
          f"{latency[int(0.9 * (len(latency) - 1))]:.2f} s (last third of the frames: median "
          f"{statistics.median(last):.2f} s); batches (size: count) {dict(sorted(sizes.items()))}")
    print("live: tracked mean 2D %.2f px, 3D %.2f mm" % errors(live))
    alone, done = run(base, iter(frames))
    later = [i for i in done if i > 0]
    rate = len(later) / (max(done[i] for i in later) - done[0])
    print(f"one at a time, as fast as they come: {rate:.2f} frames/s; tracked mean 2D %.2f px, 3D %.2f mm"
          % errors(alone))


if __name__ == "__main__":
    main()
