"""Rasterizer speed on the PyTorch3D reference scenes (../shared/reference/pytorch3d/).

Prints, per scene and backend: forward and forward+backward milliseconds (median of --runs after one warm-up,
2 threads), the peak memory of the process that ran the scene (each scene runs in a fresh process), the speed-up
over PyTorch3D's CPU rasterizer (the figures of the reference README, measured on this kind of machine), and the
speed-up over our naive dense reference (every pixel against every face, plain autograd; measured in the same
run, once, in pixel chunks: it takes minutes on the large scenes, see --naive).

    python benchmarks/bench_render.py [--runs 10] [--naive small|all|none] [--backends numba,torch]
    python benchmarks/bench_render.py --device cuda --backends torch --naive none     # on a GPU machine
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import resource
import statistics
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

SCENES = ["tubeA_256_paper", "tubeA_256_ctrnet", "tubeA_640x480_paper", "tubeA_640x480_ctrnet",
          "chainB_640x480_paper", "chainB_640x480_ctrnet"]
# PyTorch3D 0.7.9 CPU, 2 threads, median of 10 (reference README): (forward ms, forward+backward ms).
PYTORCH3D_MS = {"tubeA_256_paper": (2452, 10919), "tubeA_256_ctrnet": (2088, 2482),
                "tubeA_640x480_paper": (10583, 22796), "tubeA_640x480_ctrnet": (10439, 10503),
                "chainB_640x480_paper": (1151, 43643), "chainB_640x480_ctrnet": (1343, 5752)}
SMALL_FOR_NAIVE = {"tubeA_256_paper", "chainB_640x480_paper"}  # ~3 and ~1.5 minutes of naive work


def reference_dir() -> Path:
    return Path(os.environ.get("PIPELINE_SHARED_DIR", REPO.parent / "shared")) / "reference" / "pytorch3d"


def _load(name: str):
    import numpy as np
    import torch

    from pipeline.render import SoftRasterSettings

    ref = np.load(reference_dir() / f"{name}.npz")
    H, W = (int(s) for s in ref["image_size"])
    settings = SoftRasterSettings.from_pytorch3d(float(ref["sigma"]), float(ref["blur_radius"]), (H, W))
    return (torch.tensor(ref["verts"])[None], torch.tensor(ref["faces"]), torch.tensor(ref["K"], dtype=torch.float32),
            (H, W), settings, torch.tensor(ref["M"], dtype=torch.float32))


def _time_scene(name: str, backend: str, runs: int, naive: bool, queue, device: str = "cpu") -> None:
    import dataclasses

    import numba
    import torch

    from pipeline.camera import project_points
    from pipeline.render import render_silhouette
    from pipeline.render.reference import naive_soft_rasterize

    torch.set_num_threads(2)
    numba.set_num_threads(2)
    verts, faces, K, size, settings, target = _load(name)
    verts, faces, K, target = (t.to(device) for t in (verts, faces, K, target))
    settings = dataclasses.replace(settings, backend=backend)
    sync = torch.cuda.synchronize if device == "cuda" else (lambda: None)
    base_rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss

    def forward():
        with torch.no_grad():
            return render_silhouette(verts, faces, K, size, settings)

    def forward_backward():
        v = verts.clone().requires_grad_(True)
        ((render_silhouette(v, faces, K, size, settings)[0] - target) ** 2).sum().backward()
        return v.grad

    out = {"scene": name, "backend": backend, "device": device}
    for key, fn in (("fwd_ms", forward), ("fwd_bwd_ms", forward_backward)):
        fn()  # warm-up (and numba compilation on a fresh cache)
        sync()
        times = []
        for _ in range(runs):
            t0 = time.perf_counter()
            fn()
            sync()
            times.append(1e3 * (time.perf_counter() - t0))
        out[key] = statistics.median(times)
    out["peak_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    out["peak_extra_mb"] = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - base_rss) / 1024
    if naive:
        H, W = size
        v = verts[0].double().clone().requires_grad_(True)
        t0 = time.perf_counter()
        uv = project_points(v[None], K.double())[0]
        batch = torch.zeros(len(faces), dtype=torch.long)
        rows = max(1, 2_000_000 // (W * len(faces)))  # dense chunks of ~2M (pixel, face) pairs
        for r in range(0, H, rows):
            # The naive reference over a band of rows: shift v so the band is the image's top rows.
            shifted = uv - torch.tensor([0.0, float(r)], dtype=torch.float64)
            band = naive_soft_rasterize(shifted, v[:, 2], faces, batch, 1, (min(rows, H - r), W), settings)
            ((band[0] - target[r:r + rows].double()) ** 2).sum().backward(retain_graph=True)
        out["naive_fwd_bwd_ms"] = 1e3 * (time.perf_counter() - t0)
    queue.put(out)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", type=int, default=10)
    parser.add_argument("--naive", choices=("small", "all", "none"), default="small",
                        help="time the naive dense reference on: two scenes (default; about 5 minutes; "
                             "the 8000-face tube at 640x480 alone takes ~15 minutes), all scenes, or none")
    parser.add_argument("--backends", default="numba,torch")
    parser.add_argument("--device", choices=("cpu", "cuda"), default="cpu",
                        help="where the tensors live (cuda: the torch backend only, no naive reference)")
    parser.add_argument("--json", type=Path, help="also write the figures to this JSON file")
    args = parser.parse_args()
    if not reference_dir().is_dir():
        print(f"reference scenes not found in {reference_dir()} (set PIPELINE_SHARED_DIR)", file=sys.stderr)
        return 2
    ctx = mp.get_context("spawn")
    rows = []
    for backend in args.backends.split(","):
        for name in SCENES:
            naive = args.device == "cpu" and backend == "numba" and (
                args.naive == "all" or (args.naive == "small" and name in SMALL_FOR_NAIVE))
            queue = ctx.Queue()
            proc = ctx.Process(target=_time_scene, args=(name, backend, args.runs, naive, queue, args.device))
            proc.start()
            row = queue.get()
            proc.join()
            rows.append(row)
            p3d_f, p3d_fb = PYTORCH3D_MS[name]
            naive_txt = (f"{row['naive_fwd_bwd_ms'] / row['fwd_bwd_ms']:8.0f}x" if "naive_fwd_bwd_ms" in row
                         else "       -")
            print(f"{name:24s} {backend:6s} fwd {row['fwd_ms']:8.1f} ms  fwd+bwd {row['fwd_bwd_ms']:8.1f} ms  "
                  f"vs PyTorch3D fwd {p3d_f / row['fwd_ms']:7.0f}x fwd+bwd {p3d_fb / row['fwd_bwd_ms']:7.0f}x  "
                  f"vs naive (fwd+bwd) {naive_txt}  peak {row['peak_mb']:6.0f} MB (+{row['peak_extra_mb']:.0f})",
                  flush=True)
    print("\n| scene | backend | forward ms | fwd+bwd ms | x PyTorch3D fwd | x PyTorch3D fwd+bwd | x naive fwd+bwd |"
          " peak MB |\n|---|---|---|---|---|---|---|---|")
    for row in rows:
        p3d_f, p3d_fb = PYTORCH3D_MS[row["scene"]]
        naive = f"{row['naive_fwd_bwd_ms'] / row['fwd_bwd_ms']:.0f}" if "naive_fwd_bwd_ms" in row else "-"
        print(f"| {row['scene']} | {row['backend']} | {row['fwd_ms']:.1f} | {row['fwd_bwd_ms']:.1f} | "
              f"{p3d_f / row['fwd_ms']:.0f} | {p3d_fb / row['fwd_bwd_ms']:.0f} | {naive} | {row['peak_mb']:.0f} |")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
