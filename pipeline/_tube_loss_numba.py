"""CPU shape-fit losses in one autograd node each: ``shape_estimation._FitProblem.loss`` (``TubeLoss``) and
``_FitProblem.skeleton_loss`` (``SkeletonLoss``) from the ring centres, frames and radius profile on, forward and
backward, and ``skeleton_terms``' outline without gradient (``tube_outline``); the fit uses them for CPU tensors
with the numba renderer (``shape_estimation.FUSED_LOSS``).

In tensor operations the rendered step after the curve is about a hundred small operations and as many autograd
nodes around five compiled calls (ring radii, rasterizer, mask loss, model path): on a warm tracking frame (three
tubes at 238 x 178 working pixels) 2.7 ms forward and 1.9 ms backward a step, of which the compiled kernels take
about 2.3 ms (``docs/soft-arms.md``). Here the same compiled kernels run in a row on float64 numpy arrays, the
tube's vertices, their projection and the tube's apparent half-widths are one more compiled loop each way, and the
length, keypoint and width terms are a few array operations. Same losses and gradients as the tensor path to float
rounding (tests), and its conventions: a vertex at or behind ``MIN_DEPTH_M`` is projected at that depth and passes
no depth gradient (``camera.project_points``: ``fx``, ``fy``, ``cx``, ``cy`` of ``K``), back faces are culled
(``render_front_faces``), the soft edge's offset passes no gradient (``RenderRadii``).
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
from pipeline.shapes._rmf_numba import bezier_rmf_backward, bezier_rmf_forward

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
        mask: ``(1 or S, H, W)`` float32 or float64 target coverage (``None``: a problem without its mask, for
            the pre-fit's loss alone).
        mask_area, path_length: ``(S,)`` the loss's normalisers.
        targets: ``(K, 2)`` or ``(S, K, 2)`` keypoints (pixels); fractions: ``(K,)`` their fractions of the path.
        image_bounds: ``(4,)`` u_min, v_min, u_max, v_max of the model path's visible part.
        rim: ``(S,)`` rim offsets; focal, polygon_scale, table, radius_knots, spacing_knots: ``RenderRadii``'s.
        dense_targets: ``(D, 2)`` or ``(S, D, 2)`` the pre-fit's points along the skeleton path, dense_fractions
            ``(D,)`` their fractions of it, dense_radius ``(D,)`` or ``(S, D)`` the mask's half-widths there,
            dense_width_weight ``(D,)`` or ``(S, D)`` the width term's weights.
        length_m: the arm's length; w_mask, w_length, w_keypoint, w_width: the weights.
    """

    K: np.ndarray
    image_size: tuple[int, int]
    settings: SoftRasterSettings
    faces: np.ndarray
    angles: int
    mask: np.ndarray | None
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
    dense_targets: np.ndarray
    dense_fractions: np.ndarray
    dense_radius: np.ndarray
    dense_width_weight: np.ndarray
    length_m: float
    w_mask: float
    w_length: float
    w_keypoint: float
    w_width: float


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


@dataclasses.dataclass(frozen=True)
class _Rings:
    """The forward pass both losses share (float64 arrays): the inputs ``x``, ``n``, ``b`` ``(S, R, 3)`` and ``p``
    ``(S, n)``, ``RenderRadii``'s ``radii``, ``offsets``, ``circle``, ``fractions`` ``(S, R)``, and
    ``tube_forward``'s ``cos_phi``, ``sin_phi``, ``verts``, ``uv``, ``z``, ``centre``."""

    x: np.ndarray
    n: np.ndarray
    b: np.ndarray
    p: np.ndarray
    radii: np.ndarray
    offsets: np.ndarray
    circle: np.ndarray
    fractions: np.ndarray
    cos_phi: np.ndarray
    sin_phi: np.ndarray
    verts: np.ndarray
    uv: np.ndarray
    z: np.ndarray
    centre: np.ndarray


def _rings_forward(points, normal, binormal, profile, terms: TubeLossTerms) -> _Rings:
    """The inputs as float64 arrays (a ``ShapeError`` for NaN or inf), the rendered ring radii, the tubes' vertices
    and projections."""
    x, n, b, p = (t.detach().to(torch.float64).contiguous().numpy() for t in (points, normal, binormal, profile))
    return _rings_of_arrays(x, n, b, p, terms)


def _rings_of_arrays(x, n, b, p, terms: TubeLossTerms) -> _Rings:
    """``_rings_forward`` of float64 arrays: ring centres, normals, binormals ``(S, R, 3)``, radius profile
    ``(S, n)``."""
    if not (np.isfinite(x).all() and np.isfinite(n).all() and np.isfinite(b).all() and np.isfinite(p).all()):
        raise ShapeError("verts_cam: contains NaN or inf")
    S, R = x.shape[0], x.shape[1]
    radii, offsets, circle, fractions = (np.empty((S, R)) for _ in range(4))
    knots_r, knots_s = terms.radius_knots, terms.spacing_knots
    _radii_numba.radii_forward(x, p, terms.rim, terms.focal, terms.polygon_scale, terms.table, knots_r,
                               np.log(knots_r), knots_s, np.log(knots_s), radii, offsets, circle, fractions)
    projected = _project_tubes(x, n, b, radii, terms.K, terms.angles)
    if not (np.isfinite(projected[2]).all() and np.isfinite(projected[3]).all()):
        raise ShapeError("verts_cam: contains NaN or inf")
    return _Rings(x, n, b, p, radii, offsets, circle, fractions, *projected)


def _rings_backward(rings: _Rings, terms: TubeLossTerms, g_uv: np.ndarray, g_centre: np.ndarray
                    ) -> tuple[np.ndarray, ...]:
    """``(dL/d points, dL/d normal, dL/d binormal, dL/d profile)`` from the gradients of the projections ``g_uv (S*V,
    2)`` and ``g_centre (S, R, 2)``."""
    r = rings
    g_points, g_normal, g_binormal, g_radii = tube_backward(r.x, r.n, r.b, r.radii, r.cos_phi, r.sin_phi,
                                                            float(terms.K[0, 0]), float(terms.K[1, 1]), r.verts,
                                                            g_uv, g_centre)
    g_radius_points, g_profile = _radii_numba.radii_backward(r.x, r.p, terms.focal, terms.polygon_scale, r.offsets,
                                                             r.circle, r.fractions, g_radii)
    return g_points + g_radius_points, g_normal, g_binormal, g_profile


def _tube_loss_forward(rings: _Rings, terms: TubeLossTerms) -> tuple[np.ndarray, tuple]:
    """The rendered loss ``(S,)`` of ``_rings_forward``'s tubes, and what ``_tube_loss_backward`` needs."""
    x, uv, z, centre = rings.x, rings.uv, rings.z, rings.centre
    S, R = x.shape[0], x.shape[1]
    A = terms.angles
    V = R * A + 2

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
        length_error = _length_error(x, terms.length_m)
        loss = loss + terms.w_length * length_error[0] * length_error[0]
    path = None
    if terms.targets.shape[-2] and terms.w_keypoint > 0:
        ends = _end_rings(uv, S, R, A)
        k_count = terms.fractions.shape[0]
        path = (np.empty((S, R + 2, 2)), np.empty((S, R + 2)), np.empty((S, R + 1), np.bool_),
                np.empty((S, 2), np.int64), np.empty((S, k_count), np.int64), np.empty((S, k_count)),
                np.empty((S, k_count), np.bool_))
        located, attributes = np.empty((S, k_count, 2)), np.zeros((S, R, 0))
        _path_numba.path_forward(centre, ends, terms.image_bounds, terms.fractions, attributes, *path, located,
                                 np.empty((S, k_count, 0)))
        difference = located - terms.targets
        distance = np.sqrt((difference * difference).sum(-1) + DISTANCE_EPS2)  # (S, K)
        loss = loss + terms.w_keypoint * distance.sum(-1) / k_count / terms.path_length
        path = (ends, attributes, path, difference, distance)
    return loss, (rings, terms, fe, bbox, faces, face_batch, silhouette, one_minus, length_error, path)


def _tube_loss_backward(saved: tuple, g: np.ndarray) -> tuple[np.ndarray, ...]:
    """``(dL/d points, dL/d normal, dL/d binormal (S, R, 3), dL/d profile (S, n))`` from the loss's gradient ``g
    (S,)`` and ``_tube_loss_forward``'s ``saved``."""
    rings, terms, fe, bbox, faces, face_batch, silhouette, one_minus, length_error, path = saved
    S, R = rings.x.shape[0], rings.x.shape[1]
    A = terms.angles
    settings = terms.settings
    g_silhouette = np.empty_like(silhouette)
    _losses_numba._backward(silhouette, terms.mask, np.ones((1, 1, 1)), False,
                            np.ascontiguousarray(g * terms.w_mask / terms.mask_area), g_silhouette)
    face_grad = kernels.soft_backward(fe, bbox, face_batch, g_silhouette, one_minus, 1.0 / settings.sigma_px2,
                                      settings.cutoff_px)
    g_uv = kernels.scatter_face_grads(face_grad, faces, len(rings.verts))
    g_centre = np.zeros((S, R, 2))
    if path is not None:
        ends, attributes, arrays, difference, distance = path
        k_count = terms.fractions.shape[0]
        scale = g * terms.w_keypoint / k_count / terms.path_length  # (S,)
        g_located = scale[:, None, None] * difference / distance[..., None]
        g_centre, g_rings, _ = _path_numba.path_backward(rings.centre, ends, terms.fractions, attributes, *arrays,
                                                         np.ascontiguousarray(g_located), np.zeros((S, k_count, 0)))
        V = R * A + 2
        g_uv = g_uv.reshape(S, V, 2)
        g_uv[:, :A] += g_rings[:, 0]
        g_uv[:, (R - 1) * A: R * A] += g_rings[:, 1]
        g_uv = g_uv.reshape(S * V, 2)
    g_points, g_normal, g_binormal, g_profile = _rings_backward(rings, terms, g_uv, g_centre)
    if length_error is not None:
        error, steps, lengths = length_error
        _length_backward(g * terms.w_length * 2.0 * error, steps, lengths, terms.length_m, g_points)
    return g_points, g_normal, g_binormal, g_profile


class TubeLoss(torch.autograd.Function):
    """``(points, normal, binormal (S, R, 3), profile (S, n) metres, terms: TubeLossTerms)`` -> the rendered loss
    ``(S,)`` in the dtype of ``points``; differentiable in the first four."""

    @staticmethod
    def forward(ctx, points, normal, binormal, profile, terms: TubeLossTerms):
        loss, ctx.saved = _tube_loss_forward(_rings_forward(points, normal, binormal, profile, terms), terms)
        return torch.from_numpy(loss).to(points.dtype)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad):
        grads = _tube_loss_backward(ctx.saved, grad.detach().to(torch.float64).contiguous().numpy())
        return (*(torch.from_numpy(a).to(grad.dtype) for a in grads), None)


@dataclasses.dataclass(frozen=True)
class BezierChain:
    """What ``BezierTubeLoss`` turns a Bezier fit's parameters into tubes with (``_FitProblem.curve`` and
    ``radii``): the Bernstein weights ``(3, R, n+1)`` of the rings' curve parameters (``frames.bezier_weights``),
    the frames' ``eps`` (``FRENET_EPS``), the radius taper ``(n_rings,)`` metres and its relative tolerance."""

    weights: np.ndarray
    eps: float
    taper: np.ndarray
    tolerance: float


_NUMPY_DTYPES = {torch.float32: np.float32, torch.float64: np.float64}


def _float64(t: torch.Tensor) -> np.ndarray:
    """A CPU tensor's values as a contiguous float64 array (a numpy conversion: a few microseconds less than
    torch's on the small tensors of a step)."""
    return np.ascontiguousarray(t.detach().numpy(), dtype=np.float64)


def _tensor(a: np.ndarray, dtype: torch.dtype) -> torch.Tensor:
    """An array as a tensor of ``dtype`` (float32 or float64)."""
    return torch.from_numpy(a.astype(_NUMPY_DTYPES[dtype], copy=False))


def _clamp_slope(value: np.ndarray, bound: np.ndarray, upper: bool) -> np.ndarray:
    """The derivative of ``torch.minimum(value, bound)`` (``upper``) or ``torch.maximum`` in ``value``: 1 on its
    side of the bound, 0 past it, 1/2 at it (torch splits a tie's gradient)."""
    inside = value < bound if upper else value > bound
    return np.where(inside, 1.0, np.where(value == bound, 0.5, 0.0))


def _chain_forward(state: torch.Tensor, offsets: torch.Tensor, chain: BezierChain) -> tuple:
    """The rings of Bezier states ``(S, n+1, 3)`` and radius offsets ``(S, n_rings)`` as float64 arrays (a
    ``ShapeError`` for NaN or inf): ``(u the states, z the control points' depths (S, n+1), c the control points
    (S, n+1, 3), tiny, bezier_rmf_forward's (x, d, d2, fallback, v0, n0, axes, t, r, normal), binormal, the radius
    profile (S, n_rings), its slope in the offsets (S, n_rings))``."""
    u, o = _float64(state), _float64(offsets)
    if not (np.isfinite(u).all() and np.isfinite(o).all()):
        raise ShapeError("state: contains NaN or inf")
    z = np.exp(u[..., 2])  # (S, n+1): control points (x/z z, y/z z, z), as state_to_control_points
    c = np.ascontiguousarray(np.stack([u[..., 0] * z, u[..., 1] * z, z], axis=-1))
    tiny = float(torch.finfo(state.dtype).tiny) ** 0.5
    B, R = c.shape[0], chain.weights.shape[1]
    x, d, d2, t, r, normal, binormal = (np.empty((B, R, 3)) for _ in range(7))
    fallback, v0, n0, axes = np.empty((B, R), np.bool_), np.empty((B, 3)), np.empty((B, 3)), np.empty(B, np.int64)
    bezier_rmf_forward(c, chain.weights, chain.eps, tiny, x, d, d2, fallback, v0, n0, axes, t, r, normal, binormal)
    low, high = (1.0 - chain.tolerance) * chain.taper, (1.0 + chain.tolerance) * chain.taper
    raised = np.maximum(chain.taper + o, low)  # as _FitProblem.radii: within the tolerance of the taper
    slope = _clamp_slope(chain.taper + o, low, upper=False) * _clamp_slope(raised, high, upper=True)
    return u, z, c, tiny, (x, d, d2, fallback, v0, n0, axes, t, r, normal), binormal, np.minimum(raised, high), slope


def bezier_skeleton_terms(state: torch.Tensor, offsets: torch.Tensor, chain: BezierChain, terms: TubeLossTerms
                          ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``_FitProblem.skeleton_terms`` of Bezier states without gradient (the Levenberg-Marquardt pre-fit), from the
    states on in compiled calls: ``(the model's points at the skeleton points' fractions (S, D, 2), their apparent
    radii relative to the mask's minus 1 (S, D), the relative length errors (S,))`` in the dtype of ``state``."""
    u, z, c, tiny, frames, binormal, profile, slope = _chain_forward(state, offsets, chain)
    x = frames[0]
    rings = _rings_of_arrays(x, frames[-1], binormal, profile, terms)
    S, R, A = x.shape[0], x.shape[1], terms.angles
    apparent = np.empty((S, R, 1))
    outline_forward(rings.uv, rings.centre, rings.offsets, A, apparent[..., 0], np.empty((S, R, 2), np.int64))
    D = terms.dense_fractions.shape[0]
    located, widths = np.empty((S, D, 2)), np.empty((S, D, 1))
    _path_numba.path_forward(rings.centre, _end_rings(rings.uv, S, R, A), terms.image_bounds, terms.dense_fractions,
                             apparent, np.empty((S, R + 2, 2)), np.empty((S, R + 2)), np.empty((S, R + 1), np.bool_),
                             np.empty((S, 2), np.int64), np.empty((S, D), np.int64), np.empty((S, D)),
                             np.empty((S, D), np.bool_), located, widths)
    relative = widths[..., 0] / terms.dense_radius - 1.0
    return tuple(_tensor(a, state.dtype) for a in (located, relative, _length_error(x, terms.length_m)[0]))


def bezier_tube_loss(state: torch.Tensor, offsets: torch.Tensor, chain: BezierChain, terms: TubeLossTerms
                     ) -> tuple[np.ndarray, tuple]:
    """``BezierTubeLoss``'s forward without autograd: the loss ``(S,)`` float64 and what
    ``bezier_tube_loss_gradients`` needs."""
    u, z, c, tiny, frames, binormal, profile, slope = _chain_forward(state, offsets, chain)
    loss, saved = _tube_loss_forward(_rings_of_arrays(frames[0], frames[-1], binormal, profile, terms), terms)
    return loss, (saved, chain, u, z, c, tiny, frames, slope)


def bezier_tube_loss_gradients(saved: tuple, g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(dL/d state (S, n+1, 3), dL/d offsets (S, n_rings))`` float64 of ``L = sum_s g_s loss_s`` from
    ``bezier_tube_loss``'s ``saved`` and the weights ``g (S,)``."""
    saved, chain, u, z, c, tiny, frames, slope = saved
    g_points, g_normal, g_binormal, g_profile = _tube_loss_backward(saved, g)
    x, d, d2, fallback, v0, n0, axes, t, r, normal = frames
    g_c = bezier_rmf_backward(c, chain.weights, tiny, x, d, d2, fallback, v0, n0, axes, t, r, normal, g_points,
                              np.zeros(x.shape), g_normal, g_binormal)
    g_state = np.stack([g_c[..., 0] * z, g_c[..., 1] * z,
                        (g_c[..., 0] * u[..., 0] + g_c[..., 1] * u[..., 1] + g_c[..., 2]) * z], axis=-1)
    return g_state, g_profile * slope


class BezierTubeLoss(torch.autograd.Function):
    """``(state (S, n+1, 3), radius offsets (S, n_rings), chain: BezierChain, terms: TubeLossTerms)`` -> the rendered
    loss ``(S,)`` of a Bezier fit's states (``shape_estimation.control_points_to_state``: each control point's ray
    ``x/z``, ``y/z`` and ``log z``) in their dtype, differentiable in the first two: ``TubeLoss`` of
    ``_FitProblem.curve``'s rings (rotation-minimising frames) and ``radii``'s profile, the whole chain in one node
    (a warm tracking step's curve, radii and their autograd nodes took about a sixth of its time)."""

    @staticmethod
    def forward(ctx, state, offsets, chain: BezierChain, terms: TubeLossTerms):
        loss, ctx.saved = bezier_tube_loss(state, offsets, chain, terms)
        return _tensor(loss, state.dtype)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad):
        g_state, g_offsets = bezier_tube_loss_gradients(ctx.saved, _float64(grad))
        return (_tensor(g_state, grad.dtype), _tensor(g_offsets, grad.dtype) if ctx.needs_input_grad[1] else None,
                None, None)


@nb.njit(inline="always", **_JIT)
def _across(centre, s, i):
    """Ring ``i``'s neighbours ``lo``, ``hi`` (clipped at the ends), the projected centreline's central difference
    ``f = c_hi - c_lo`` and ``1 / |f|`` (softened): the direction across the tube is ``(-f_v, f_u) / |f|``."""
    R = centre.shape[1]
    lo = i - 1 if i > 0 else 0
    hi = i + 1 if i < R - 1 else R - 1
    fu = centre[s, hi, 0] - centre[s, lo, 0]
    fv = centre[s, hi, 1] - centre[s, lo, 1]
    return lo, hi, fu, fv, 1.0 / math.sqrt(fu * fu + fv * fv + 1e-12)


@nb.njit(**_JIT)
def outline_forward(uv, centre, offsets, angles, apparent, extremes):
    """The tubes' half-widths in the image (``_FitProblem.apparent_radii``) from ``tube_forward``'s projections:
    fill ``apparent (S, R)`` with half the projected ring's extent across the projected centreline (its direction by
    central differences) plus the soft edge's ``offsets (S, R)``, and ``extremes (S, R, 2)`` with the ring vertices
    (angle indices) of the largest and the smallest extent."""
    S, R = centre.shape[0], centre.shape[1]
    V = R * angles + 2
    for s in range(S):
        for i in range(R):
            lo, hi, fu, fv, inv = _across(centre, s, i)
            nu, nv = -fv * inv, fu * inv
            most, least = -np.inf, np.inf
            for j in range(angles):
                k = s * V + i * angles + j
                across = (uv[k, 0] - centre[s, i, 0]) * nu + (uv[k, 1] - centre[s, i, 1]) * nv
                if across > most:
                    most = across
                    extremes[s, i, 0] = j
                if across < least:
                    least = across
                    extremes[s, i, 1] = j
            apparent[s, i] = 0.5 * (most - least) + offsets[s, i]


@nb.njit(**_JIT)
def outline_backward(uv, centre, angles, extremes, g_apparent, g_uv, g_centre):
    """Add the gradients of ``outline_forward``'s ``apparent`` to those of the projections ``g_uv (S*V, 2)`` and
    ``g_centre (S, R, 2)``. With ``a = (u_max - u_min) . n / 2`` and ``n = m / |m|``, ``m = (-f_v, f_u)`` the central
    difference turned a quarter: the extreme vertices get ``+-g n / 2``, the centre nothing (it cancels), and ``n``
    passes ``g (u_max - u_min) / 2`` to the neighbouring centres through ``f``."""
    S, R = centre.shape[0], centre.shape[1]
    V = R * angles + 2
    for s in range(S):
        for i in range(R):
            g = g_apparent[s, i]
            if g == 0.0:
                continue
            lo, hi, fu, fv, inv = _across(centre, s, i)
            nu, nv = -fv * inv, fu * inv
            kmax = s * V + i * angles + extremes[s, i, 0]
            kmin = s * V + i * angles + extremes[s, i, 1]
            g_uv[kmax, 0] += 0.5 * g * nu
            g_uv[kmax, 1] += 0.5 * g * nv
            g_uv[kmin, 0] -= 0.5 * g * nu
            g_uv[kmin, 1] -= 0.5 * g * nv
            gnu = 0.5 * g * (uv[kmax, 0] - uv[kmin, 0])  # dL/dn
            gnv = 0.5 * g * (uv[kmax, 1] - uv[kmin, 1])
            g_inv = gnu * -fv + gnv * fu  # n = m inv
            cube = inv * inv * inv
            g_fu = gnv * inv - g_inv * cube * fu
            g_fv = -gnu * inv - g_inv * cube * fv
            g_centre[s, hi, 0] += g_fu
            g_centre[s, hi, 1] += g_fv
            g_centre[s, lo, 0] -= g_fu
            g_centre[s, lo, 1] -= g_fv


def _project_tubes(x, n, b, radii, K, angles):
    """``tube_forward`` on float64 arrays: ``(cos_phi, sin_phi, verts, uv, z, centre)``."""
    S, R = x.shape[0], x.shape[1]
    V = R * angles + 2
    phi = np.arange(angles) * (2.0 * math.pi / angles)
    cos_phi, sin_phi = np.cos(phi), np.sin(phi)
    verts, uv, z, centre = np.empty((S * V, 3)), np.empty((S * V, 2)), np.empty(S * V), np.empty((S, R, 2))
    tube_forward(x, n, b, radii, cos_phi, sin_phi, float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]),
                 verts, uv, z, centre)
    return cos_phi, sin_phi, verts, uv, z, centre


def _end_rings(uv: np.ndarray, S: int, R: int, angles: int) -> np.ndarray:
    """The base and tip rings' projected vertices ``(S, 2, A, 2)`` of ``tube_forward``'s ``uv``."""
    rings = uv.reshape(S, R * angles + 2, 2)
    return np.ascontiguousarray(np.stack([rings[:, :angles], rings[:, (R - 1) * angles: R * angles]], axis=1))


def tube_outline(points: torch.Tensor, normal: torch.Tensor, binormal: torch.Tensor, radii: torch.Tensor,
                 offsets: torch.Tensor, K: torch.Tensor, angles: int) -> tuple[torch.Tensor, ...]:
    """The pre-fit's view of tubes without gradient (the Levenberg-Marquardt pre-fit): ``(centre (S, R, 2), ends
    (S, 2, A, 2), apparent (S, R))`` (``_FitProblem.apparent_radii`` and the projections ``model_keypoints`` takes)
    in the dtype of ``points``, from ring centres and frames ``(S, R, 3)``, rendered radii and edge offsets ``(S,
    R)`` and the intrinsics ``K (3, 3)``."""
    x, n, b, r, o = (t.detach().to(torch.float64).contiguous().numpy() for t in (points, normal, binormal, radii,
                                                                                  offsets))
    S, R = x.shape[0], x.shape[1]
    *_, uv, _, centre = _project_tubes(x, n, b, r, K.detach().to(torch.float64).numpy(), angles)
    apparent = np.empty((S, R))
    outline_forward(uv, centre, o, angles, apparent, np.empty((S, R, 2), np.int64))
    return tuple(torch.from_numpy(a).to(points.dtype) for a in (centre, _end_rings(uv, S, R, angles), apparent))


def _length_error(x: np.ndarray, length_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(l - L) / L`` ``(S,)`` of the polylines through ``x (S, R, 3)``, with their steps ``(S, R-1, 3)`` and the
    steps' lengths ``(S, R-1)``."""
    steps = x[:, 1:] - x[:, :-1]
    lengths = np.sqrt((steps * steps).sum(-1) + STEP_EPS)
    return (lengths.sum(-1) - length_m) / length_m, steps, lengths


def _length_backward(g_error: np.ndarray, steps: np.ndarray, lengths: np.ndarray, length_m: float,
                     g_points: np.ndarray) -> None:
    """Add the gradient of ``_length_error`` (``g_error (S,)``) to ``g_points (S, R, 3)``."""
    g_steps = (g_error / length_m)[:, None, None] * steps / lengths[..., None]
    g_points[:, 1:] += g_steps
    g_points[:, :-1] -= g_steps


class SkeletonLoss(torch.autograd.Function):
    """``(points, normal, binormal (S, R, 3), profile (S, n) metres, terms: TubeLossTerms)`` -> the pre-fit's loss
    ``(S,)`` (``_FitProblem.skeleton_loss``: the model path against the skeleton's points, the widths, the length)
    in the dtype of ``points``; differentiable in the first four."""

    @staticmethod
    def forward(ctx, points, normal, binormal, profile, terms: TubeLossTerms):
        rings = _rings_forward(points, normal, binormal, profile, terms)
        x, uv, centre = rings.x, rings.uv, rings.centre
        S, R = x.shape[0], x.shape[1]
        A = terms.angles
        apparent, extremes = np.empty((S, R, 1)), np.empty((S, R, 2), np.int64)
        outline_forward(uv, centre, rings.offsets, A, apparent[..., 0], extremes)
        ends = _end_rings(uv, S, R, A)
        D = terms.dense_fractions.shape[0]
        arrays = (np.empty((S, R + 2, 2)), np.empty((S, R + 2)), np.empty((S, R + 1), np.bool_),
                  np.empty((S, 2), np.int64), np.empty((S, D), np.int64), np.empty((S, D)), np.empty((S, D), np.bool_))
        located, widths = np.empty((S, D, 2)), np.empty((S, D, 1))
        _path_numba.path_forward(centre, ends, terms.image_bounds, terms.dense_fractions, apparent, *arrays, located,
                                 widths)
        difference = located - terms.dense_targets
        distance = np.sqrt((difference * difference).sum(-1) + DISTANCE_EPS2)  # (S, D)
        relative = widths[..., 0] / terms.dense_radius - 1.0  # (S, D)
        length_error, steps, lengths = _length_error(x, terms.length_m)
        loss = (distance.sum(-1) / (D * terms.path_length) + terms.w_length * length_error * length_error
                + terms.w_width * (terms.dense_width_weight * relative * relative).sum(-1))
        ctx.saved = (rings, terms, apparent, extremes, ends, arrays, difference, distance, relative, length_error,
                     steps, lengths)
        return torch.from_numpy(loss).to(points.dtype)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad):
        (rings, terms, apparent, extremes, ends, arrays, difference, distance, relative, length_error, steps,
         lengths) = ctx.saved
        g = grad.detach().to(torch.float64).contiguous().numpy()
        S, R = rings.x.shape[0], rings.x.shape[1]
        A = terms.angles
        D = terms.dense_fractions.shape[0]
        g_located = (g / (D * terms.path_length))[:, None, None] * difference / distance[..., None]
        g_relative = g[:, None] * terms.w_width * 2.0 * terms.dense_width_weight * relative  # (S, D)
        g_widths = np.ascontiguousarray((g_relative / terms.dense_radius)[..., None])
        g_centre, g_ends, g_apparent = _path_numba.path_backward(rings.centre, ends, terms.dense_fractions, apparent,
                                                                 *arrays, np.ascontiguousarray(g_located), g_widths)
        V = R * A + 2
        g_uv = np.zeros((S, V, 2))
        g_uv[:, :A] = g_ends[:, 0]
        g_uv[:, (R - 1) * A: R * A] = g_ends[:, 1]
        g_uv = g_uv.reshape(S * V, 2)
        outline_backward(rings.uv, rings.centre, A, extremes, np.ascontiguousarray(g_apparent[..., 0]), g_uv,
                         g_centre)
        g_points, g_normal, g_binormal, g_profile = _rings_backward(rings, terms, g_uv, g_centre)
        _length_backward(g * terms.w_length * 2.0 * length_error, steps, lengths, terms.length_m, g_points)
        dtype = grad.dtype
        return (torch.from_numpy(g_points).to(dtype), torch.from_numpy(g_normal).to(dtype),
                torch.from_numpy(g_binormal).to(dtype), torch.from_numpy(g_profile).to(dtype), None)
