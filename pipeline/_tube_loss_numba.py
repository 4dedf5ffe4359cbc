"""CPU rendered shape-fit loss in one autograd node: ``shape_estimation._FitProblem.loss`` from the ring centres,
frames and radius profile on, forward and backward (the fit uses it for CPU tensors with the numba renderer).

In tensor operations the step after the curve is about a hundred small operations and as many autograd nodes
around five compiled calls (ring radii, rasterizer, mask loss, model path): on a warm tracking frame (three tubes
at 238 x 178 working pixels) 2.7 ms forward and 1.9 ms backward a step, of which the compiled kernels take about
2.3 ms (``docs/tracking.md``). Here the same compiled kernels run in a row on float64 numpy arrays, the tube's
vertices and their projection are one more compiled loop each way, and the length and keypoint terms are a few
array operations: one autograd node. Same loss and gradients as the tensor path to float rounding (tests), and
its conventions: a vertex at or behind ``MIN_DEPTH_M`` is projected at that depth and passes no depth gradient
(``camera.project_points``), back faces are culled (``render_front_faces``).
"""

from __future__ import annotations

import dataclasses
import math

import numba as nb
import numpy as np
import torch
from torch.autograd.function import once_differentiable

from pipeline import _losses_numba, _path_numba, _radii_numba
from pipeline.errors import ShapeError
from pipeline.render import _numba_kernels as kernels
from pipeline.render.settings import SoftRasterSettings

_JIT = dict(cache=True, nogil=True, fastmath=False)

MIN_DEPTH_M = 1e-6  # camera.project_points' default min_depth
STEP_EPS = 1e-18  # added to a step's squared length before its square root (``_FitProblem.length_error``)
DISTANCE_EPS2 = 1e-18  # losses._smooth_abs: eps**2 with eps = 1e-9


@dataclasses.dataclass(frozen=True)
class TubeLossTerms:
    """What the loss compares the tubes with, and its weights (float64 numpy unless said; ``S`` starts).

    Fields:
        K: ``(3, 3)`` intrinsics of the working image; image_size: ``(H, W)``.
        settings: the rasterizer's (back faces are culled whatever it says).
        faces: ``(F, 3)`` int64 faces of one tube (``tube_faces``); angles: vertices per ring.
        mask: ``(1 or S, H, W)`` float32 or float64 target coverage.
        mask_area, path_length: ``(S,)`` the loss's normalisers.
        targets: ``(K, 2)`` or ``(S, K, 2)`` keypoints (pixels); fractions: ``(K,)`` their fractions of the path.
        image_bounds: ``(4,)`` u_min, v_min, u_max, v_max of the model path's visible part.
        rim: ``(S,)`` rim offsets; focal, polygon_scale, table, radius_knots, spacing_knots: ``RenderRadii``'s.
        length_m: the arm's length; w_mask, w_length, w_keypoint: the weights.
    """

    K: np.ndarray
    image_size: tuple[int, int]
    settings: SoftRasterSettings
    faces: np.ndarray
    angles: int
    mask: np.ndarray
    mask_area: np.ndarray
    path_length: np.ndarray
    targets: np.ndarray
    fractions: np.ndarray
    image_bounds: np.ndarray
    rim: np.ndarray
    focal: float
    polygon_scale: float
    table: np.ndarray
    radius_knots: np.ndarray
    spacing_knots: np.ndarray
    length_m: float
    w_mask: float
    w_length: float
    w_keypoint: float


@nb.njit(**_JIT)
def tube_forward(points, normal, binormal, radii, cos_phi, sin_phi, fx, fy, cx, cy, verts, uv, z, centre):
    """Fill ``verts (S*V, 3)`` (``tube_vertices``' rings then cap centres, per start), their projections ``uv (S*V,
    2)`` and depths ``z (S*V,)``, and the ring centres' projections ``centre (S, R, 2)``, from ``points``,
    ``normal``, ``binormal (S, R, 3)`` and rendered ``radii (S, R)``; ``V = R * A + 2``."""
    S, R = points.shape[0], points.shape[1]
    A = cos_phi.shape[0]
    V = R * A + 2
    for s in range(S):
        for i in range(R):
            r = radii[s, i]
            for j in range(A):
                k = s * V + i * A + j
                for c in range(3):
                    verts[k, c] = points[s, i, c] + r * (binormal[s, i, c] * sin_phi[j] - normal[s, i, c] * cos_phi[j])
        for c in range(3):
            verts[s * V + R * A, c] = points[s, 0, c]
            verts[s * V + R * A + 1, c] = points[s, R - 1, c]
        for i in range(R):
            depth = points[s, i, 2] if points[s, i, 2] > MIN_DEPTH_M else MIN_DEPTH_M
            centre[s, i, 0] = fx * (points[s, i, 0] / depth) + cx
            centre[s, i, 1] = fy * (points[s, i, 1] / depth) + cy
    for k in range(S * V):
        depth = verts[k, 2] if verts[k, 2] > MIN_DEPTH_M else MIN_DEPTH_M
        uv[k, 0] = fx * (verts[k, 0] / depth) + cx
        uv[k, 1] = fy * (verts[k, 1] / depth) + cy
        z[k] = verts[k, 2]


@nb.njit(inline="always", **_JIT)
def _project_back(x, y, depth, gu, gv, fx, fy, out):
    """Add the gradient of a point's projection ``(gu, gv)`` to ``out (3,)`` (the depth's only above the floor)."""
    if depth > MIN_DEPTH_M:
        out[0] += gu * fx / depth
        out[1] += gv * fy / depth
        out[2] -= (gu * fx * x + gv * fy * y) / (depth * depth)
    else:
        out[0] += gu * fx / MIN_DEPTH_M
        out[1] += gv * fy / MIN_DEPTH_M


@nb.njit(**_JIT)
def tube_backward(points, normal, binormal, radii, cos_phi, sin_phi, fx, fy, verts, g_uv, g_centre):
    """``(dL/d points, dL/d normal, dL/d binormal (S, R, 3), dL/d radii (S, R))`` from the gradients of
    ``tube_forward``'s ``uv`` and ``centre``."""
    S, R = points.shape[0], points.shape[1]
    A = cos_phi.shape[0]
    V = R * A + 2
    g_points = np.zeros(points.shape)
    g_normal = np.zeros(points.shape)
    g_binormal = np.zeros(points.shape)
    g_radii = np.zeros(radii.shape)
    g = np.empty(3)
    for s in range(S):
        for i in range(R):
            r = radii[s, i]
            for j in range(A):
                k = s * V + i * A + j
                g[:] = 0.0
                _project_back(verts[k, 0], verts[k, 1], verts[k, 2], g_uv[k, 0], g_uv[k, 1], fx, fy, g)
                for c in range(3):
                    g_points[s, i, c] += g[c]
                    g_radii[s, i] += g[c] * (binormal[s, i, c] * sin_phi[j] - normal[s, i, c] * cos_phi[j])
                    g_normal[s, i, c] -= g[c] * r * cos_phi[j]
                    g_binormal[s, i, c] += g[c] * r * sin_phi[j]
            g[:] = 0.0
            _project_back(points[s, i, 0], points[s, i, 1], points[s, i, 2], g_centre[s, i, 0], g_centre[s, i, 1],
                          fx, fy, g)
            for c in range(3):
                g_points[s, i, c] += g[c]
        for end, i in ((0, 0), (1, R - 1)):
            k = s * V + R * A + end
            g[:] = 0.0
            _project_back(verts[k, 0], verts[k, 1], verts[k, 2], g_uv[k, 0], g_uv[k, 1], fx, fy, g)
            for c in range(3):
                g_points[s, i, c] += g[c]
    return g_points, g_normal, g_binormal, g_radii


def _packed_faces(faces: np.ndarray, starts: int, n_verts: int) -> tuple[np.ndarray, np.ndarray]:
    """One tube's faces repeated for ``starts`` tubes of ``n_verts`` vertices: ``(S*F, 3)`` and their start
    ``(S*F,)``."""
    offsets = np.arange(starts, dtype=np.int64) * n_verts
    packed = (faces[None] + offsets[:, None, None]).reshape(-1, 3)
    return np.ascontiguousarray(packed), np.repeat(np.arange(starts, dtype=np.int64), len(faces))


class TubeLoss(torch.autograd.Function):
    """``(points, normal, binormal (S, R, 3), profile (S, n) metres, terms: TubeLossTerms)`` -> the rendered loss
    ``(S,)`` in the dtype of ``points``; differentiable in the first four."""

    @staticmethod
    def forward(ctx, points, normal, binormal, profile, terms: TubeLossTerms):
        dtype = points.dtype
        x, n, b, p = (t.detach().to(torch.float64).contiguous().numpy() for t in (points, normal, binormal, profile))
        if not (np.isfinite(x).all() and np.isfinite(n).all() and np.isfinite(b).all() and np.isfinite(p).all()):
            raise ShapeError("verts_cam: contains NaN or inf")
        S, R = x.shape[0], x.shape[1]
        A = terms.angles
        V = R * A + 2
        radii, offsets, circle, fractions = (np.empty((S, R)) for _ in range(4))
        knots_r, knots_s = terms.radius_knots, terms.spacing_knots
        _radii_numba.radii_forward(x, p, terms.rim, terms.focal, terms.polygon_scale, terms.table, knots_r,
                                   np.log(knots_r), knots_s, np.log(knots_s), radii, offsets, circle, fractions)
        phi = np.arange(A) * (2.0 * math.pi / A)
        cos_phi, sin_phi = np.cos(phi), np.sin(phi)
        K = terms.K
        fx, fy, cx, cy = float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
        verts, uv, z, centre = np.empty((S * V, 3)), np.empty((S * V, 2)), np.empty(S * V), np.empty((S, R, 2))
        tube_forward(x, n, b, radii, cos_phi, sin_phi, fx, fy, cx, cy, verts, uv, z, centre)
        if not (np.isfinite(verts).all() and np.isfinite(uv).all()):
            raise ShapeError("verts_cam: contains NaN or inf")

        # the soft silhouettes of the front faces, as SoftRasterizeNumba draws them
        H, W = terms.image_size
        settings = terms.settings
        faces, face_batch = _packed_faces(terms.faces, S, V)
        fe, bbox = kernels.face_setup(uv, z, faces, H, W, float(settings.cutoff_px), settings.near_m,
                                      settings.min_face_area_px2, True)
        bins, ids = kernels.bin_faces(bbox, face_batch, S, H, W, settings.tile_size)
        silhouette, one_minus = np.empty((S, H, W)), np.empty((S, H, W))
        kernels.soft_forward(fe, bbox, bins, ids, S, H, W, settings.tile_size, 1.0 / settings.sigma_px2,
                             settings.cutoff_px, settings.saturation, nb.get_num_threads(), silhouette, one_minus,
                             np.empty((1, 1, 1), np.bool_), False, False)
        mask_term = np.empty(S)
        ones = np.ones((1, 1, 1))
        _losses_numba._forward(silhouette, terms.mask, ones, False, mask_term)
        loss = terms.w_mask * mask_term / terms.mask_area

        length_error = None
        if terms.w_length > 0:
            steps = x[:, 1:] - x[:, :-1]
            lengths = np.sqrt((steps * steps).sum(-1) + STEP_EPS)  # (S, R-1)
            length_error = (lengths.sum(-1) - terms.length_m) / terms.length_m
            loss = loss + terms.w_length * length_error * length_error
        path = None
        if terms.targets.shape[-2] and terms.w_keypoint > 0:
            rings = uv.reshape(S, V, 2)
            rings = np.ascontiguousarray(np.stack([rings[:, :A], rings[:, (R - 1) * A: R * A]], axis=1))
            k_count = terms.fractions.shape[0]
            path = (np.empty((S, R + 2, 2)), np.empty((S, R + 2)), np.empty((S, R + 1), np.bool_),
                    np.empty((S, 2), np.int64), np.empty((S, k_count), np.int64), np.empty((S, k_count)),
                    np.empty((S, k_count), np.bool_))
            located, attributes = np.empty((S, k_count, 2)), np.zeros((S, R, 0))
            _path_numba.path_forward(centre, rings, terms.image_bounds, terms.fractions, attributes, *path, located,
                                     np.empty((S, k_count, 0)))
            difference = located - terms.targets
            distance = np.sqrt((difference * difference).sum(-1) + DISTANCE_EPS2)  # (S, K)
            loss = loss + terms.w_keypoint * distance.sum(-1) / k_count / terms.path_length
            path = (rings, attributes, path, difference, distance)
        ctx.saved = (x, n, b, p, terms, radii, offsets, circle, fractions, cos_phi, sin_phi, verts, centre, fe, bbox,
                     faces, face_batch, silhouette, one_minus, length_error, path)
        return torch.from_numpy(loss).to(dtype)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad):
        (x, n, b, p, terms, radii, offsets, circle, fractions, cos_phi, sin_phi, verts, centre, fe, bbox, faces,
         face_batch, silhouette, one_minus, length_error, path) = ctx.saved
        g = grad.detach().to(torch.float64).contiguous().numpy()
        S, R = x.shape[0], x.shape[1]
        A = terms.angles
        settings = terms.settings
        g_silhouette = np.empty_like(silhouette)
        _losses_numba._backward(silhouette, terms.mask, np.ones((1, 1, 1)), False,
                                np.ascontiguousarray(g * terms.w_mask / terms.mask_area), g_silhouette)
        face_grad = kernels.soft_backward(fe, bbox, face_batch, g_silhouette, one_minus, 1.0 / settings.sigma_px2,
                                          settings.cutoff_px)
        g_uv = kernels.scatter_face_grads(face_grad, faces, len(verts))
        g_centre = np.zeros((S, R, 2))
        if path is not None:
            rings, attributes, arrays, difference, distance = path
            k_count = terms.fractions.shape[0]
            scale = g * terms.w_keypoint / k_count / terms.path_length  # (S,)
            g_located = scale[:, None, None] * difference / distance[..., None]
            g_centre, g_rings, _ = _path_numba.path_backward(centre, rings, terms.fractions, attributes, *arrays,
                                                             np.ascontiguousarray(g_located), np.zeros((S, k_count, 0)))
            V = R * A + 2
            g_uv = g_uv.reshape(S, V, 2)
            g_uv[:, :A] += g_rings[:, 0]
            g_uv[:, (R - 1) * A: R * A] += g_rings[:, 1]
            g_uv = g_uv.reshape(S * V, 2)
        K = terms.K
        g_points, g_normal, g_binormal, g_radii = tube_backward(x, n, b, radii, cos_phi, sin_phi, float(K[0, 0]),
                                                                float(K[1, 1]), verts, g_uv, g_centre)
        g_radius_points, g_profile = _radii_numba.radii_backward(x, p, terms.focal, terms.polygon_scale, offsets,
                                                                 circle, fractions, g_radii)
        g_points += g_radius_points
        if length_error is not None:
            steps = x[:, 1:] - x[:, :-1]
            lengths = np.sqrt((steps * steps).sum(-1) + STEP_EPS)
            g_steps = (g * terms.w_length * 2.0 * length_error / terms.length_m)[:, None, None] * steps / lengths[..., None]
            g_points[:, 1:] += g_steps
            g_points[:, :-1] -= g_steps
        dtype = grad.dtype
        return (torch.from_numpy(g_points).to(dtype), torch.from_numpy(g_normal).to(dtype),
                torch.from_numpy(g_binormal).to(dtype), torch.from_numpy(g_profile).to(dtype), None)


@nb.njit(**_JIT)
def outline_forward(points, normal, binormal, radii, offsets, cos_phi, sin_phi, fx, fy, cx, cy, centre, ends,
                    apparent):
    """The pre-fit's view of tubes (``_FitProblem.apparent_radii`` and the projections ``model_keypoints`` takes),
    forward only: fill ``centre (S, R, 2)`` (the projected ring centres), ``ends (S, 2, A, 2)`` (the base and tip
    rings' projected vertices) and ``apparent (S, R)`` (half the projected ring's extent across the projected
    centreline, by central differences, plus the soft edge's ``offsets (S, R)``)."""
    S, R = points.shape[0], points.shape[1]
    A = cos_phi.shape[0]
    ring = np.empty((A, 2))
    for s in range(S):
        for i in range(R):
            depth = points[s, i, 2] if points[s, i, 2] > MIN_DEPTH_M else MIN_DEPTH_M
            centre[s, i, 0] = fx * (points[s, i, 0] / depth) + cx
            centre[s, i, 1] = fy * (points[s, i, 1] / depth) + cy
        for i in range(R):
            lo = i - 1 if i > 0 else 0
            hi = i + 1 if i < R - 1 else R - 1
            fu = centre[s, hi, 0] - centre[s, lo, 0]
            fv = centre[s, hi, 1] - centre[s, lo, 1]
            inv = 1.0 / math.sqrt(fu * fu + fv * fv + 1e-12)
            nu, nv = -fv * inv, fu * inv
            r = radii[s, i]
            most, least = -np.inf, np.inf
            for j in range(A):
                x = points[s, i, 0] + r * (binormal[s, i, 0] * sin_phi[j] - normal[s, i, 0] * cos_phi[j])
                y = points[s, i, 1] + r * (binormal[s, i, 1] * sin_phi[j] - normal[s, i, 1] * cos_phi[j])
                z = points[s, i, 2] + r * (binormal[s, i, 2] * sin_phi[j] - normal[s, i, 2] * cos_phi[j])
                depth = z if z > MIN_DEPTH_M else MIN_DEPTH_M
                ring[j, 0] = fx * (x / depth) + cx
                ring[j, 1] = fy * (y / depth) + cy
                across = (ring[j, 0] - centre[s, i, 0]) * nu + (ring[j, 1] - centre[s, i, 1]) * nv
                most = max(most, across)
                least = min(least, across)
            apparent[s, i] = 0.5 * (most - least) + offsets[s, i]
            if i == 0 or i == R - 1:
                end = 0 if i == 0 else 1
                for j in range(A):
                    ends[s, end, j, 0] = ring[j, 0]
                    ends[s, end, j, 1] = ring[j, 1]


def tube_outline(points: torch.Tensor, normal: torch.Tensor, binormal: torch.Tensor, radii: torch.Tensor,
                 offsets: torch.Tensor, K: torch.Tensor, angles: int) -> tuple[torch.Tensor, ...]:
    """``outline_forward`` on tensors (no gradient): ``(centre (S, R, 2), ends (S, 2, A, 2), apparent (S, R))`` in
    the dtype of ``points``, from ring centres and frames ``(S, R, 3)``, rendered radii and edge offsets ``(S, R)``
    and the intrinsics ``K (3, 3)``."""
    x, n, b, r, o = (t.detach().to(torch.float64).contiguous().numpy() for t in (points, normal, binormal, radii,
                                                                                  offsets))
    S, R = x.shape[0], x.shape[1]
    phi = np.arange(angles) * (2.0 * math.pi / angles)
    k = K.detach().to(torch.float64).numpy()
    centre, ends, apparent = np.empty((S, R, 2)), np.empty((S, 2, angles, 2)), np.empty((S, R))
    outline_forward(x, n, b, r, o, np.cos(phi), np.sin(phi), float(k[0, 0]), float(k[1, 1]), float(k[0, 2]),
                    float(k[1, 2]), centre, ends, apparent)
    return tuple(torch.from_numpy(a).to(points.dtype) for a in (centre, ends, apparent))
