"""One rendered step of the shape fit, as a tracking batch runs it: tube silhouettes and the mask loss, forward and
backward, now against the way it was done before 2026-11-27 (session 24), in the same run.

- ``now``: ``render_front_faces`` (back faces culled in the rasterizer's face set-up) and ``mask_loss`` (one
  compiled pass each way on CPU tensors).
- ``before``: the front faces chosen in torch (a gather of every face's corners, a cross product, ``nonzero``)
  and rendered packed, and the mask loss in tensor operations. (The kernels' unzeroed output buffers, the third
  change of that session, are in both.)

The scene: ``--tubes`` bent tubes (32 rings of 16 vertices, the fit's mesh) on a ``--height`` x ``--width`` working
image (the defaults are a batch of 8 warm frames with two starts each plus two retries: 18 at 202 x 231). Prints the
median milliseconds of ``--runs`` steps after a warm-up, the ratio, and that both give the same loss and gradient.

    OMP_NUM_THREADS=2 NUMBA_NUM_THREADS=2 python benchmarks/bench_shape_step.py [--tubes 18] [--runs 50]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pipeline.render import SoftRasterSettings, render_silhouette_packed, single_torch_thread  # noqa: E402
from pipeline.shape_estimation import render_front_faces  # noqa: E402
from pipeline.shapes.tube import bezier_tube_vertices, tube_faces  # noqa: E402


def before(verts: torch.Tensor, faces: torch.Tensor, K: torch.Tensor, size: tuple[int, int],
           settings: SoftRasterSettings, mask: torch.Tensor) -> torch.Tensor:
    B, V, _ = verts.shape
    with torch.no_grad():
        corners = verts[:, faces]
        normal = torch.linalg.cross(corners[:, :, 1] - corners[:, :, 0], corners[:, :, 2] - corners[:, :, 0], dim=-1)
        batch, face = torch.nonzero((normal * corners.sum(dim=2)).sum(-1) < 0, as_tuple=True)
        packed = faces[face] + (batch * V)[:, None]
    silhouette = render_silhouette_packed(verts.reshape(B * V, 3), packed, torch.arange(B).repeat_interleave(V), K,
                                          B, size, settings)
    return ((silhouette - mask) ** 2).sum(dim=(-2, -1))


def now(verts, faces, K, size, settings, mask):
    from pipeline.losses import mask_loss

    return mask_loss(render_front_faces(verts, faces, K, size, settings), mask)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tubes", type=int, default=18)
    parser.add_argument("--height", type=int, default=202)
    parser.add_argument("--width", type=int, default=231)
    parser.add_argument("--runs", type=int, default=50)
    args = parser.parse_args()
    H, W = args.height, args.width
    g = torch.Generator().manual_seed(0)
    f = 0.55 * W
    K = torch.tensor([[f, 0.0, (W - 1) / 2], [0.0, f, (H - 1) / 2], [0.0, 0.0, 1.0]])
    base = torch.tensor([[-0.07, 0.03, 0.40], [0.0, -0.04, 0.43], [0.07, 0.02, 0.46]])
    control = base + 0.01 * torch.randn(args.tubes, 3, 3, generator=g)
    radii = torch.linspace(0.014, 0.006, 32).expand(args.tubes, 32)
    verts0 = bezier_tube_vertices(control, radii, n_angles=16).float()
    faces = tube_faces(32, 16)
    settings = SoftRasterSettings.from_sigma(0.25)
    with torch.no_grad(), single_torch_thread():
        mask = (render_front_faces(verts0[:1] * torch.tensor([1.01, 1.0, 1.0]), faces, K, (H, W), settings)[0]
                > 0.5).float()
    results = {}
    with single_torch_thread():
        for name, step in (("before", before), ("now", now)):
            times = []
            for run in range(args.runs + 1):
                verts = verts0.clone().requires_grad_(True)
                t = time.perf_counter()
                loss = step(verts, faces, K, (H, W), settings, mask)
                loss.sum().backward()
                if run:
                    times.append((time.perf_counter() - t) * 1e3)
            results[name] = (statistics.median(times), loss.detach(), verts.grad)
    (t_before, loss_before, grad_before), (t_now, loss_now, grad_now) = results["before"], results["now"]
    print(f"{args.tubes} tubes at {H}x{W}, {torch.get_num_threads()} torch threads outside the fit: one step "
          f"(render + mask loss, forward and backward), median of {args.runs}")
    print(f"  before {t_before:.2f} ms, now {t_now:.2f} ms: {t_before / t_now:.2f}x")
    loss_gap = float(((loss_now - loss_before).abs() / loss_before.abs().clamp_min(1e-12)).max())
    grad_gap = float((grad_now - grad_before).abs().max() / grad_before.abs().max().clamp_min(1e-12))
    print(f"  same result: loss relative difference {loss_gap:.1e}, gradient {grad_gap:.1e} of its largest entry")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
