"""CPU backend: the numba kernels of ``_numba_kernels`` behind a torch autograd Function."""

from __future__ import annotations

import os

import numba
import numpy as np
import torch
from torch.autograd.function import once_differentiable

from pipeline.render import _numba_kernels as kernels
from pipeline.render.settings import SoftRasterSettings

# Threading layer: OpenMP first. numba's OpenMP layer loads the libgomp that torch has already loaded, so the
# kernels and torch's tensor code share one pool of workers; with the `workqueue` layer (or tbb) the two pools fight
# for the cores (torch's idle workers spin for a while after each parallel op), which made a forward render up to
# 2x slower right after a large tensor op (benchmarks/bench_render.py, 2 cores). Applies unless the user chose a
# layer (NUMBA_THREADING_LAYER, e.g. `workqueue` on a machine shared with other CPU-heavy jobs, where spinning
# workers cost more than they save), and only if no numba parallel code ran before this import.
if "NUMBA_THREADING_LAYER" not in os.environ and numba.config.THREADING_LAYER == "default":
    numba.config.THREADING_LAYER_PRIORITY = ["omp", "tbb", "workqueue"]


def start_workers() -> int:
    """Start numba's worker threads (once per process; later calls do nothing) and return their count."""
    return numba.get_num_threads()


def _as_numpy(uv, z, faces, face_batch):
    """The kernels' inputs: float64 geometry, int64 indices, contiguous numpy arrays."""
    return (uv.detach().to(torch.float64).contiguous().numpy(), z.detach().to(torch.float64).contiguous().numpy(),
            faces.to(torch.int64).contiguous().numpy(), face_batch.to(torch.int64).contiguous().numpy())


def _setup(uv, z, faces, face_batch, B, image_size, settings, cutoff):
    """Edge records, bounding boxes and tile bins of the packed faces (numpy, float64 geometry)."""
    H, W = image_size
    uv_np, z_np, faces_np, batch_np = _as_numpy(uv, z, faces, face_batch)
    fe, bbox = kernels.face_setup(uv_np, z_np, faces_np, H, W, float(cutoff), settings.near_m,
                                  settings.min_face_area_px2, settings.cull_back_faces)
    offsets, ids = kernels.bin_faces(bbox, batch_np, B, H, W, settings.tile_size)
    return fe, bbox, offsets, ids, faces_np, batch_np


class SoftRasterizeNumba(torch.autograd.Function):
    """uv (N, 2), z (N,), faces (F, 3), face_batch (F,) -> (S (B, H, W), hard (B, H, W) bool, or (0,) when not
    ``want_hard``); gradient w.r.t. uv only. With ``straight_through`` the first output's value is the hard
    silhouette's (0 or 1), its gradient S's."""

    @staticmethod
    def forward(ctx, uv, z, faces, face_batch, B, image_size, settings: SoftRasterSettings, want_hard: bool = False,
                straight_through: bool = False):
        H, W = image_size
        fe, bbox, offsets, ids, faces_np, batch_np = _setup(uv, z, faces, face_batch, B, image_size, settings,
                                                            settings.cutoff_px)
        dtype = uv.dtype if uv.dtype in (torch.float32, torch.float64) else torch.float32
        # numpy buffers that the kernel fills, every pixel it reads later (not zeroed first: zeroing the three was
        # about a millisecond of a tracking batch's 5 ms render, docs/renderer.md)
        silhouette = np.empty((B, H, W), dtype=np.float64 if dtype == torch.float64 else np.float32)
        one_minus = np.empty((B, H, W))
        want_hard = want_hard or straight_through
        hard = np.empty((B, H, W) if want_hard else (1, 1, 1), dtype=np.bool_)
        kernels.soft_forward(fe, bbox, offsets, ids, B, H, W, settings.tile_size, 1.0 / settings.sigma_px2,
                             settings.cutoff_px, settings.saturation, numba.get_num_threads(), silhouette,
                             one_minus, hard, bool(want_hard), bool(straight_through))
        silhouette = torch.from_numpy(silhouette)
        hard = torch.from_numpy(hard) if want_hard else torch.zeros(0, dtype=torch.bool)
        ctx.saved = (fe, bbox, faces_np, batch_np, one_minus, settings, uv.shape[0])
        ctx.mark_non_differentiable(z, hard)
        return silhouette.to(uv.dtype), hard

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_silhouette, grad_hard=None):
        fe, bbox, faces_np, batch_np, one_minus, settings, n_verts = ctx.saved
        if grad_silhouette.dtype not in (torch.float32, torch.float64):
            grad_silhouette = grad_silhouette.to(torch.float64)
        grad_np = grad_silhouette.detach().contiguous().numpy()
        face_grad = kernels.soft_backward(fe, bbox, batch_np, grad_np, one_minus, 1.0 / settings.sigma_px2,
                                          settings.cutoff_px)
        grad_uv = kernels.scatter_face_grads(face_grad, faces_np, n_verts)
        return torch.from_numpy(grad_uv).to(grad_silhouette.dtype), None, None, None, None, None, None, None, None


# Faces per face set-up of a hard render: a larger batch (the pose fit scores 512 rotations of about 1500 hull faces
# at once) is drawn a group of whole images at a time, so that the edge records (176 bytes a face) stay in memory
# the allocator reuses: one set-up of 760 000 faces spent most of its 70 ms faulting in 130 MB of fresh pages.
HARD_CHUNK_FACES = 1 << 16


def hard(uv, z, faces, face_batch, B, image_size, settings: SoftRasterSettings) -> torch.Tensor:
    """Binary coverage (B, H, W) bool of the packed faces (drawn in groups of whole images of at most
    ``HARD_CHUNK_FACES`` faces, or of one image, when the faces come grouped by image as packed batches do)."""
    H, W = image_size
    out = np.zeros((B, H, W), np.bool_)
    uv_np, z_np, faces_np, batch_np = _as_numpy(uv, z, faces, face_batch)
    grouped = batch_np.size < 2 or bool((batch_np[1:] >= batch_np[:-1]).all())
    starts = np.searchsorted(batch_np, np.arange(B + 1)) if grouped else np.array([0, batch_np.size])
    b0 = 0
    while b0 < B:
        b1 = B
        if grouped:  # whole images, at least one, at most HARD_CHUNK_FACES faces unless one image has more
            b1 = max(b0 + 1, int(np.searchsorted(starts, starts[b0] + HARD_CHUNK_FACES, side="right")) - 1)
        f0, f1 = (int(starts[b0]), int(starts[b1])) if grouped else (0, batch_np.size)
        fe, bbox = kernels.face_setup(uv_np, z_np, faces_np[f0:f1], H, W, 0.0, settings.near_m,
                                      settings.min_face_area_px2, settings.cull_back_faces)
        offsets, ids = kernels.bin_faces(bbox, batch_np[f0:f1] - b0, b1 - b0, H, W, settings.tile_size)
        kernels.hard_forward(fe, bbox, offsets, ids, b1 - b0, H, W, settings.tile_size, numba.get_num_threads(),
                             out[b0:b1])
        b0 = b1
    return torch.from_numpy(out)
