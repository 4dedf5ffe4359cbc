"""Segmenter accuracy and speed: held-out IoU of the shipped ONNX model per robot, and ms per 640x480 frame.

Held-out images are fresh 640x480 draws of the training generator (models/segmenters/train.py: random colours,
lighting, clutter, photometric changes) from seeds the training never used; IoU is per image, then averaged.
Speed: the whole segmenter call (pre-processing, onnxruntime on the CPU, resize, decision) on one 640x480 frame,
median of --runs after 2 warm-up calls, at each thread count of --threads. The colour segmenter is timed too.

    python benchmarks/bench_segment.py [--model robot_deeplab] [--held-out 60] [--runs 20] [--threads 1,2]
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import statistics
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
os.environ.setdefault("NUMBA_NUM_THREADS", "1")  # the synthetic renders' rasterizer; keep it off the timed cores


def load_train_module():
    spec = importlib.util.spec_from_file_location("segmenter_train", REPO / "models" / "segmenters" / "train.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def time_call(segmenter, image, runs: int) -> float:
    for _ in range(2):
        segmenter(image)
    times = []
    for _ in range(runs):
        start = time.perf_counter()
        segmenter(image)
        times.append(1000.0 * (time.perf_counter() - start))
    return statistics.median(times)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--model", default="robot_deeplab", help="ONNX model name or folder")
    parser.add_argument("--held-out", type=int, default=60, help="images per robot")
    parser.add_argument("--seed", type=int, default=0, help="training seed the held-out seeds are offset from")
    parser.add_argument("--runs", type=int, default=20)
    parser.add_argument("--threads", default="1,2", help="onnxruntime thread counts to time")
    args = parser.parse_args()


    from pipeline.segment import ColorSegmenter, OnnxSegmenter, OnnxSegmenterConfig, color_preset

    train = load_train_module()
    maker = train.SampleMaker()
    segmenter = OnnxSegmenter(OnnxSegmenterConfig(model=args.model, device="cpu", num_threads=1))
    print(f"model {segmenter.model_path} ({segmenter.model_path.stat().st_size / 1e6:.2f} MB)")
    frame = None
    for kind in ("soft_arm", "manipulator"):
        samples = train.held_out_set(maker, kind, args.held_out, args.seed)
        result = train.evaluate_segmenter(segmenter, samples)
        print(f"held-out {kind:11s}: mean IoU {result['mean_iou']:.4f}  median {result['median_iou']:.4f}  "
              f"min {result['min_iou']:.4f}  ({result['count']} images 640x480)")  # fmt: skip
        frame = samples[0][0]
    assert frame is not None and frame.shape == (480, 640, 3)
    for threads in (int(t) for t in args.threads.split(",")):
        timed = OnnxSegmenter(OnnxSegmenterConfig(model=args.model, device="cpu", num_threads=threads))
        ms = time_call(timed, frame, args.runs)
        print(f"onnx  640x480: {ms:7.2f} ms/frame (median of {args.runs}, {threads} onnxruntime thread(s), CPU)")
    ms = time_call(ColorSegmenter(color_preset("soft_arm")), frame, args.runs)
    print(f"color 640x480: {ms:7.2f} ms/frame (median of {args.runs}, OpenCV)")
    print(f"cpu cores: {os.cpu_count()}, load average {os.getloadavg()[0]:.1f} (other jobs slow the timings)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
