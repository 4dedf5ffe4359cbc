"""Naive dense soft silhouette: every pixel against every face, plain autograd, float64.

The executable definition the fast backends are tested against (values and gradients), and the baseline of
``benchmarks/bench_render.py``. Memory is O(B * H * W * F): tiny scenes only.
"""

from __future__ import annotations

import torch

from pipeline.render.settings import SoftRasterSettings


def naive_soft_rasterize(
    uv: torch.Tensor,
    z: torch.Tensor,
    faces: torch.Tensor,
    face_batch: torch.Tensor,
    batch_size: int,
    image_size: tuple[int, int],
    settings: SoftRasterSettings,
) -> torch.Tensor:
    """Same contract as ``pipeline.render.soft_rasterize``: uv (N, 2) px, z (N,), faces (F, 3), face_batch (F,)
    -> (B, H, W). Distances by brute force over the three edge segments; no binning, no saturation."""
    H, W = image_size
    v, u = torch.meshgrid(torch.arange(H, dtype=uv.dtype), torch.arange(W, dtype=uv.dtype), indexing="ij")
    p = torch.stack([u, v], dim=-1).reshape(-1, 1, 2)  # (P, 1, 2) pixel centres
    c = uv[faces]  # (F, 3, 2)
    area2 = (c[:, 1, 0] - c[:, 0, 0]) * (c[:, 2, 1] - c[:, 0, 1]) - (c[:, 1, 1] - c[:, 0, 1]) * (c[:, 2, 0] - c[:, 0, 0])
    drawn = (z[faces] >= settings.near_m).all(dim=1) & (area2.abs() * 0.5 > settings.min_face_area_px2)
    if settings.cull_back_faces:
        drawn = drawn & (area2 <= 0)
    d2 = torch.full((p.shape[0], faces.shape[0]), float("inf"), dtype=uv.dtype)
    edge_fn = []
    for k in range(3):
        a, b = c[None, :, k], c[None, :, (k + 1) % 3]  # (1, F, 2)
        e = b - a
        t = (((p - a) * e).sum(-1) / (e**2).sum(-1).clamp_min(1e-30)).clamp(0, 1)
        d2 = torch.minimum(d2, ((p - a - t[..., None] * e) ** 2).sum(-1))
        edge_fn.append((e[..., 0] * (p[..., 1] - a[..., 1]) - e[..., 1] * (p[..., 0] - a[..., 0]))
                       * torch.sign(area2))
    inside = (torch.stack(edge_fn) > 0).all(dim=0)  # (P, F)
    counted = drawn[None] & (inside | (d2 < settings.cutoff_px**2))
    x = torch.where(inside, d2, -d2) / settings.sigma_px2
    log_keep = torch.where(counted, torch.nn.functional.logsigmoid(-x), torch.zeros_like(x))  # log(1 - p_f)
    out = []
    for b in range(batch_size):
        mine = (face_batch == b)[None]
        out.append(-torch.expm1(torch.where(mine, log_keep, torch.zeros_like(log_keep)).sum(-1)).reshape(H, W))
    return torch.stack(out)
