"""Device-agnostic backend in plain tensor ops (CPU or CUDA), chunked, with a hand-written backward.

Faces are binned into square tiles by their cut-off-expanded bounding boxes; each (tile, face) pair expands to the
tile's pixels inside the face's box. Candidates are processed in chunks of at most ``max_pairs_per_chunk``
(pixel, face) pairs, so memory stays bounded whatever the mesh and image size. The backward recomputes each chunk
instead of storing per-pair intermediates.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import torch
import torch.nn.functional as F_

from pipeline.render.settings import SoftRasterSettings


@dataclass(frozen=True)
class _Faces:
    """Per drawn face: corners a_k (F, 3, 2), edges e_k = a_{k+1} - a_k (F, 3, 2), 1/|e_k|^2 (F, 3), unit inward
    normals (F, 3, 2), pixel boxes (F, 4) = (i0, i1, j0, j1), image index (F,), and ``index`` (F,) into the
    caller's face list."""

    corners: torch.Tensor
    edges: torch.Tensor
    inv_len2: torch.Tensor
    normals: torch.Tensor
    bbox: torch.Tensor
    batch: torch.Tensor
    index: torch.Tensor


def _face_records(uv, z, faces, face_batch, image_size, settings: SoftRasterSettings, cutoff: float) -> _Faces:
    H, W = image_size
    corners = uv.detach().to(torch.float64)[faces]  # (F, 3, 2)
    edges = corners.roll(-1, dims=1) - corners  # edge k: corner k -> corner k+1
    area2 = edges[:, 0, 0] * (-edges[:, 2, 1]) - edges[:, 0, 1] * (-edges[:, 2, 0])  # (c1 - c0) x (c2 - c0)
    lo = corners.amin(dim=1) - cutoff  # (F, 2)
    hi = corners.amax(dim=1) + cutoff
    i0 = torch.ceil(lo[:, 1]).clamp(min=0)
    i1 = torch.floor(hi[:, 1]).clamp(max=H - 1)
    j0 = torch.ceil(lo[:, 0]).clamp(min=0)
    j1 = torch.floor(hi[:, 0]).clamp(max=W - 1)
    keep = (
        (z.detach()[faces] >= settings.near_m).all(dim=1)
        & (area2.abs() * 0.5 > settings.min_face_area_px2)
        & ~(settings.cull_back_faces & (area2 > 0))
        & (i0 <= i1)
        & (j0 <= j1)
    )
    index = keep.nonzero().squeeze(1)
    corners, edges, area2 = corners[index], edges[index], area2[index]
    len2 = (edges**2).sum(-1)  # (F, 3), > 0 for a face of non-zero area
    orient = torch.sign(area2)[:, None, None]
    normals = torch.stack([-edges[..., 1], edges[..., 0]], dim=-1) * orient / len2.sqrt()[..., None]
    bbox = torch.stack([i0[index], i1[index], j0[index], j1[index]], dim=1).long()
    return _Faces(corners, edges, 1.0 / len2, normals, bbox, face_batch[index], index)


def _candidates(fr: _Faces, image_size, tile: int, max_pairs: int, cutoff: float) -> Iterator[tuple[torch.Tensor, ...]]:
    """Yield chunks (face (Q,), i (Q,), j (Q,)) of (face, pixel) candidates: pixels of the face's box, in tiles
    that come within ``cutoff`` of the face."""
    H, W = image_size
    device = fr.bbox.device
    t0 = fr.bbox // tile  # tile ranges (F, 4)
    n_ty = t0[:, 1] - t0[:, 0] + 1
    n_tx = t0[:, 3] - t0[:, 2] + 1
    counts = n_ty * n_tx
    face = torch.repeat_interleave(torch.arange(len(counts), device=device), counts)  # (T,) one per (tile, face)
    start = torch.repeat_interleave(counts.cumsum(0) - counts, counts)
    r = torch.arange(len(face), device=device) - start
    ty = t0[face, 0] + r // n_tx[face]
    tx = t0[face, 2] + r % n_tx[face]
    # Drop (tile, face) pairs where the tile lies wholly beyond one edge line by the cut-off (thin, slanted faces
    # have large boxes): the farthest-inside corner of the tile along that edge's normal decides.
    n = fr.normals[face]  # (T, 3, 2)
    corner = torch.stack([tx[:, None] * tile + torch.where(n[..., 0] > 0, tile - 1, 0),
                          ty[:, None] * tile + torch.where(n[..., 1] > 0, tile - 1, 0)], dim=-1)  # (T, 3, 2)
    reach = ((corner - fr.corners[face]) * n).sum(-1)  # (T, 3) largest edge-line value over the tile
    keep = (reach > -cutoff).all(dim=1)
    face, ty, tx = face[keep], ty[keep], tx[keep]
    offs = torch.arange(tile, device=device)
    step = max(1, max_pairs // (tile * tile))
    for s in range(0, len(face), step):
        f = face[s:s + step, None, None]  # (P, 1, 1)
        i = ty[s:s + step, None, None] * tile + offs[None, :, None]  # (P, T, 1)
        j = tx[s:s + step, None, None] * tile + offs[None, None, :]  # (P, 1, T)
        box = fr.bbox[f.squeeze(-1).squeeze(-1)]  # (P, 4)
        inside = ((i >= box[:, 0, None, None]) & (i <= box[:, 1, None, None])
                  & (j >= box[:, 2, None, None]) & (j <= box[:, 3, None, None]))  # (P, T, T)
        f, i, j = (x.expand_as(inside)[inside] for x in (f, i, j))
        yield f, i, j


def _pair_geometry(fr: _Faces, f, i, j, cutoff: float):
    """For candidates (Q,): keep those where the face counts; return (f, i, j, inside, d2, k, t, r) with r the
    vector from the closest boundary point to the pixel (Q, 2)."""
    p = torch.stack([j, i], dim=-1).to(torch.float64)  # (Q, 2) = (u, v)
    a = fr.corners[f]  # (Q, 3, 2)
    lines = ((p[:, None, :] - a) * fr.normals[f]).sum(-1)  # (Q, 3) signed distance to each edge line
    near = (lines > -cutoff).all(dim=1)
    f, i, j, p, a, lines = f[near], i[near], j[near], p[near], a[near], lines[near]
    e = fr.edges[f]
    t = (((p[:, None, :] - a) * e).sum(-1) * fr.inv_len2[f]).clamp(0.0, 1.0)  # (Q, 3)
    r_all = p[:, None, :] - (a + t[..., None] * e)  # (Q, 3, 2)
    seg2 = (r_all**2).sum(-1)
    inside = (lines > 0).all(dim=1)
    # Outside, the nearest boundary point lies on an edge whose line the pixel is beyond; inside, on the nearest
    # edge line (the foot of the perpendicular, so seg2 there equals lines^2).
    key = torch.where(inside[:, None], lines, torch.where(lines <= 0, seg2, torch.full_like(seg2, float("inf"))))
    k = key.argmin(dim=1)
    d2 = seg2.gather(1, k[:, None]).squeeze(1)
    counted = inside | (d2 < cutoff * cutoff)
    rows = torch.arange(len(k), device=k.device)
    return (f[counted], i[counted], j[counted], inside[counted], d2[counted], k[counted],
            t[rows, k][counted], r_all[rows, k][counted])


class SoftRasterizeTorch(torch.autograd.Function):
    """uv (N, 2), z (N,), faces (F, 3), face_batch (F,) -> S (B, H, W); gradient w.r.t. uv only."""

    @staticmethod
    def forward(ctx, uv, z, faces, face_batch, B, image_size, settings: SoftRasterSettings):
        H, W = image_size
        fr = _face_records(uv, z, faces, face_batch, image_size, settings, settings.cutoff_px)
        acc = torch.zeros(B * H * W, dtype=torch.float64, device=uv.device)  # -log(1 - S)
        for f, i, j in _candidates(fr, image_size, settings.tile_size, settings.max_pairs_per_chunk,
                                   settings.cutoff_px):
            f, i, j, inside, d2, _, _, _ = _pair_geometry(fr, f, i, j, settings.cutoff_px)
            x = torch.where(inside, d2, -d2) / settings.sigma_px2
            acc.index_add_(0, (fr.batch[f] * H + i) * W + j, F_.softplus(x))
        acc = acc.view(B, H, W)
        saturated = acc > settings.saturation
        silhouette = torch.where(saturated, torch.ones_like(acc), -torch.expm1(-acc))
        one_minus = torch.where(saturated, torch.zeros_like(acc), torch.exp(-acc))
        ctx.save_for_backward(one_minus)
        ctx.fr, ctx.faces, ctx.n_verts, ctx.image_size, ctx.settings = fr, faces, uv.shape[0], image_size, settings
        ctx.mark_non_differentiable(z)
        return silhouette.to(uv.dtype)

    @staticmethod
    def backward(ctx, grad_silhouette):
        (one_minus,) = ctx.saved_tensors
        fr, faces, settings = ctx.fr, ctx.faces, ctx.settings
        H, W = ctx.image_size
        weight = (grad_silhouette.to(torch.float64) * one_minus).reshape(-1)  # dL/dS * (1 - S)
        corner_grad = torch.zeros(len(fr.index) * 3, 2, dtype=torch.float64, device=weight.device)
        for f, i, j in _candidates(fr, ctx.image_size, settings.tile_size, settings.max_pairs_per_chunk,
                                   settings.cutoff_px):
            f, i, j, inside, d2, k, t, r = _pair_geometry(fr, f, i, j, settings.cutoff_px)
            w = weight[(fr.batch[f] * H + i) * W + j]
            x = torch.where(inside, d2, -d2) / settings.sigma_px2
            g_d2 = w * torch.sigmoid(x) / settings.sigma_px2 * torch.where(inside, 1.0, -1.0)  # dL/d(d2)
            g = -2.0 * r * g_d2[:, None]  # (Q, 2), split between the edge's two corners
            corner_grad.index_add_(0, f * 3 + k, g * (1.0 - t)[:, None])
            corner_grad.index_add_(0, f * 3 + (k + 1) % 3, g * t[:, None])
        grad_uv = torch.zeros(ctx.n_verts, 2, dtype=torch.float64, device=weight.device)
        grad_uv.index_add_(0, faces[fr.index].reshape(-1), corner_grad)
        return grad_uv.to(grad_silhouette.dtype), None, None, None, None, None, None


def hard(uv, z, faces, face_batch, B, image_size, settings: SoftRasterSettings) -> torch.Tensor:
    """Binary coverage (B, H, W) bool of the packed faces."""
    H, W = image_size
    fr = _face_records(uv, z, faces, face_batch, image_size, settings, 0.0)
    out = torch.zeros(B * H * W, dtype=torch.bool, device=uv.device)
    for f, i, j in _candidates(fr, image_size, settings.tile_size, settings.max_pairs_per_chunk, 0.0):
        p = torch.stack([j, i], dim=-1).to(torch.float64)
        lines = ((p[:, None, :] - fr.corners[f]) * fr.normals[f]).sum(-1)
        hit = (lines > 0).all(dim=1)
        out[((fr.batch[f] * H + i) * W + j)[hit]] = True
    return out.view(B, H, W)
