"""Soft silhouette rasterizer (SoftRas / PyTorch3D ``SoftSilhouetteShader`` without per-pixel truncation).

For pixel centre ``p`` and projected triangle ``f`` let ``d`` be the distance from ``p`` to the triangle's boundary,
negative inside ("inside" = all barycentric coordinates > 0). A face counts when ``p`` is inside or ``d`` is below
the cut-off; its probability is ``p_f = sigmoid(-sign(d) d^2 / sigma)`` and ``S(p) = 1 - prod_f (1 - p_f)``.

Two backends compute the same thing:
- ``numba``: compiled CPU kernels (tiles in parallel, per-pixel early stop at saturation; per-face backward).
- ``torch``: tensor ops on any device: (tile, face) pairs expanded to (pixel, face) candidates, processed in chunks
  of at most ``settings.max_pairs_per_chunk``, with a hand-written backward that recomputes each chunk.
Both take projected vertices; the public functions project camera-frame vertices with ``pipeline.camera``.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import torch

from pipeline.camera import project_points
from pipeline.checks import check_finite, check_image_size, check_shape
from pipeline.errors import ShapeError
from pipeline.render.settings import SoftRasterSettings

__all__ = ["render_silhouette", "render_silhouette_packed", "render_hard", "soft_rasterize"]


def render_silhouette(
    verts_cam: torch.Tensor,
    faces: torch.Tensor,
    K: torch.Tensor,
    image_size: tuple[int, int],
    settings: SoftRasterSettings = SoftRasterSettings(),
) -> torch.Tensor:
    """Soft silhouettes of a batch of meshes that share one face list.

    Convention: OpenCV camera frame (x right, y down, z forward), metres; pixel centres at integer (u, v).

    Args:
        verts_cam: (B, V, 3) vertices in the camera frame.
        faces: (F, 3) int64 vertex indices, shared by the batch.
        K: (3, 3) or (B, 3, 3) pinhole intrinsics of the (undistorted) camera at ``image_size``.
        image_size: (H, W) pixels.
        settings: softness, cut-off, near plane, backend.

    Returns:
        (B, H, W) soft silhouette in [0, 1], differentiable w.r.t. ``verts_cam`` (and ``K``).
    """
    verts_packed, faces_packed, verts_batch = _pack(verts_cam, faces)
    return render_silhouette_packed(verts_packed, faces_packed, verts_batch, K, verts_cam.shape[0], image_size,
                                    settings)


def render_silhouette_packed(
    verts_cam: torch.Tensor,
    faces: torch.Tensor,
    verts_batch: torch.Tensor,
    K: torch.Tensor,
    batch_size: int,
    image_size: tuple[int, int],
    settings: SoftRasterSettings = SoftRasterSettings(),
    *,
    return_hard: bool = False,
    straight_through: bool = False,
) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
    """Soft silhouettes of meshes of different sizes, concatenated.

    Args:
        verts_cam: (N, 3) vertices of all meshes, camera frame, metres.
        faces: (F, 3) int64 indices into ``verts_cam`` (each face's vertices belong to one mesh).
        verts_batch: (N,) int64 image index in [0, batch_size) of each vertex.
        K: (3, 3) or (batch_size, 3, 3) intrinsics.
        batch_size: number of images B.
        image_size: (H, W).
        return_hard: also return the hard silhouettes of the same faces (see :func:`soft_rasterize`).
        straight_through: the first result's value is the hard silhouette's, its gradient the soft one's (see
            :func:`soft_rasterize`).

    Returns:
        (B, H, W) soft silhouettes, or ``(soft, hard (B, H, W) bool)`` with ``return_hard``.
    """
    uv, z, face_batch = _project_packed(verts_cam, faces, verts_batch, K, batch_size)
    return soft_rasterize(uv, z, faces, face_batch, batch_size, image_size, settings, return_hard=return_hard,
                          straight_through=straight_through)


def render_hard(
    verts_cam: torch.Tensor,
    faces: torch.Tensor,
    K: torch.Tensor,
    image_size: tuple[int, int],
    settings: SoftRasterSettings = SoftRasterSettings(),
) -> torch.Tensor:
    """Binary silhouettes (B, H, W) bool: pixel centres strictly inside a face in front of the near plane.

    Same arguments as :func:`render_silhouette`; only ``near_m``, ``min_face_area_px2``, ``cull_back_faces``,
    ``tile_size`` and ``backend`` of ``settings`` matter. Not differentiable (for overlays and synthetic masks).
    """
    H, W = check_image_size(image_size)
    verts_packed, faces_packed, verts_batch = _pack(verts_cam, faces)
    B = verts_cam.shape[0]
    with torch.no_grad():
        uv, z, face_batch = _project_packed(verts_packed, faces_packed, verts_batch, K, B)
        if _use_numba(settings, uv):
            from pipeline.render import _numba_backend

            return _numba_backend.hard(uv, z, faces_packed, face_batch, B, (H, W), settings)
        from pipeline.render import _torch_backend

        return _torch_backend.hard(uv, z, faces_packed, face_batch, B, (H, W), settings)


def soft_rasterize(
    uv: torch.Tensor,
    z: torch.Tensor,
    faces: torch.Tensor,
    face_batch: torch.Tensor,
    batch_size: int,
    image_size: tuple[int, int],
    settings: SoftRasterSettings = SoftRasterSettings(),
    *,
    return_hard: bool = False,
    straight_through: bool = False,
) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
    """The rasterizer on projected vertices (the differentiable core).

    Args:
        uv: (N, 2) pixel coordinates (u = column, v = row) of all vertices.
        z: (N,) camera depth of each vertex (metres); only used to cull faces nearer than ``settings.near_m``.
        faces: (F, 3) int64 indices into ``uv``.
        face_batch: (F,) int64 image index of each face.
        batch_size: B.
        image_size: (H, W).
        return_hard: also return the hard silhouette of the same faces, ``render_hard``'s value (pixel centres
            strictly inside a face): on the CPU backend one pass gives both (the straight-through estimator of
            the pose fit needs both at every step; one pass saves the hard render's own face set-up, binning and
            raster).
        straight_through: the straight-through estimator: the first result's value is the hard silhouette (0 or
            1, as floats), its gradient the soft silhouette's, i.e. ``soft + (hard - soft).detach()``, which is
            ``hard`` bit for bit (for ``s`` in [0, 1] and ``h`` in {0, 1}, ``s + (h - s)`` rounds to ``h``); the CPU
            backend writes it in the same pass, without the three tensor operations.

    Returns:
        (B, H, W) soft silhouette, dtype of ``uv``; differentiable w.r.t. ``uv`` (hand-written backward); with
        ``return_hard``, ``(soft, hard (B, H, W) bool)``.
    """
    H, W = check_image_size(image_size)
    dims = check_shape(uv, ("N", 2), "uv")
    check_shape(z, (dims["N"],), "z")
    _check_faces(faces, dims["N"], "faces")
    check_shape(face_batch, (faces.shape[0],), "face_batch")
    if not isinstance(batch_size, int) or batch_size < 1:
        raise ShapeError(f"batch_size: expected a positive int, got {batch_size!r}")
    if faces.shape[0] and (int(face_batch.min()) < 0 or int(face_batch.max()) >= batch_size):
        raise ShapeError(f"face_batch: expected indices in [0, {batch_size}), got [{int(face_batch.min())}, "
                         f"{int(face_batch.max())}]")
    check_finite(uv, "uv (projected vertices)")
    check_finite(z, "z (vertex depths)")
    if _use_numba(settings, uv):
        from pipeline.render import _numba_backend

        soft, hard = _numba_backend.SoftRasterizeNumba.apply(uv, z, faces, face_batch, batch_size, (H, W), settings,
                                                             return_hard, straight_through)
        return (soft, hard) if return_hard else soft
    from pipeline.render import _torch_backend

    soft = _torch_backend.SoftRasterizeTorch.apply(uv, z, faces, face_batch, batch_size, (H, W), settings)
    if not (return_hard or straight_through):
        return soft
    with torch.no_grad():
        hard = _torch_backend.hard(uv.detach(), z, faces, face_batch, batch_size, (H, W), settings)
    if straight_through:
        soft = soft + (hard.to(soft.dtype) - soft).detach()
    return (soft, hard) if return_hard else soft


def _pack(verts_cam: torch.Tensor, faces: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(B, V, 3) vertices sharing (F, 3) faces -> packed (B*V, 3) vertices, (B*F, 3) faces, (B*V,) image index."""
    dims = check_shape(verts_cam, ("B", "V", 3), "verts_cam")
    B, V = dims["B"], dims["V"]
    _check_faces(faces, V, "faces")
    offsets = torch.arange(B, device=faces.device, dtype=faces.dtype) * V
    faces_packed = (faces[None] + offsets[:, None, None]).reshape(-1, 3)  # (B*F, 3)
    verts_batch = torch.arange(B, device=verts_cam.device).repeat_interleave(V)  # (B*V,)
    return verts_cam.reshape(B * V, 3), faces_packed, verts_batch


def _use_numba(settings: SoftRasterSettings, uv: torch.Tensor) -> bool:
    if settings.backend == "numba":
        if uv.device.type != "cpu":
            raise ShapeError(f"backend 'numba' runs on CPU tensors, got a tensor on {uv.device}; use 'torch' "
                             f"or 'auto'")
        return True
    return settings.backend == "auto" and uv.device.type == "cpu"


def _project_packed(
    verts_cam: torch.Tensor, faces: torch.Tensor, verts_batch: torch.Tensor, K: torch.Tensor, batch_size: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Project packed vertices with their image's K: returns uv (N, 2), z (N,), face_batch (F,)."""
    N = check_shape(verts_cam, ("N", 3), "verts_cam")["N"]
    _check_faces(faces, N, "faces")
    check_shape(verts_batch, (N,), "verts_batch")
    check_finite(verts_cam, "verts_cam")
    if K.dim() == 2:
        check_shape(K, (3, 3), "K")
        uv = project_points(verts_cam[None], K.to(verts_cam))[0]
    else:
        check_shape(K, (batch_size, 3, 3), "K")
        uv = project_points(verts_cam[:, None], K.to(verts_cam)[verts_batch])[:, 0]
    face_batch = verts_batch[faces[:, 0]] if faces.shape[0] else verts_batch.new_zeros(0)
    return uv, verts_cam[:, 2], face_batch


def _check_faces(faces: torch.Tensor, n_verts: int, name: str) -> None:
    check_shape(faces, (None, 3), name)
    if faces.dtype not in (torch.int64, torch.int32):
        raise ShapeError(f"{name}: expected an int64 tensor of vertex indices, got {faces.dtype}")
    if faces.numel() and (int(faces.min()) < 0 or int(faces.max()) >= n_verts):
        raise ShapeError(f"{name}: vertex indices must lie in [0, {n_verts}), got [{int(faces.min())}, "
                         f"{int(faces.max())}]")


@contextlib.contextmanager
def single_torch_thread() -> Iterator[None]:
    """Run the block with torch on one thread (the fits' tensors are small), the caller's thread count restored
    afterwards, with the CPU renderer's worker threads started first.

    numba's OpenMP layer sets the process's OpenMP thread count when it starts its workers, and torch reads that
    count: started inside the block, they switched torch back to all cores in the middle of a process's first fit,
    whose float32 sums, split over another number of threads, then rounded differently from every later fit's."""
    from pipeline.render import _numba_backend

    threads = torch.get_num_threads()  # the caller's, restored afterwards
    _numba_backend.start_workers()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)
