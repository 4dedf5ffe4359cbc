"""Orthonormal frames along space curves: Frenet-Serret (as in the paper) and rotation-minimising (the default).

Convention: every frame is right-handed, ``(tangent, normal, binormal)`` with ``binormal = tangent x normal``;
all vectors are unit ``(B, S, 3)`` tensors in the frame of the curve (the camera frame for a centreline).
The tube mesh (``pipeline.shapes.tube``) puts the surface at ``p + r (-N cos(phi) + B sin(phi))``.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
import torch

from pipeline.checks import check_choice, check_positive, check_shape, numba_path
from pipeline.errors import ShapeError
from pipeline.shapes._rmf_numba import BezierRotationMinimizingFrames, RotationMinimizingFrames
from pipeline.shapes.bezier import _check_s, _order, bernstein_basis, bezier_derivative, bezier_points

__all__ = [
    "Frames",
    "unit",
    "FRAME_METHODS",
    "frenet_frames",
    "frenet_degenerate",
    "initial_normal",
    "rotation_minimizing_frames",
    "bezier_frames",
]

FRAME_METHODS = ("rmf", "frenet")

# Frenet frames are refused where the tangent turns by less than this many radians per unit s (|p' x p''| / |p'|^2).
FRENET_EPS = 1e-6


class Frames(NamedTuple):
    """Frames at ``S`` samples of ``B`` curves; each field ``(B, S, 3)``, unit length, right-handed."""

    tangent: torch.Tensor
    normal: torch.Tensor
    binormal: torch.Tensor


def frenet_degenerate(d1: torch.Tensor, d2: torch.Tensor, eps: float = FRENET_EPS) -> torch.Tensor:
    """Where the Frenet frame is undefined: ``|p' x p''| <= eps * |p'|^2`` (straight parts, inflections, cusps).

    ``|p' x p''| / |p'|^2 = kappa |p'|`` is the angle (radians) the tangent turns per unit ``s``, so the test does
    not depend on the curve's scale or units.

    Args:
        d1: ``(B, S, 3)`` first derivatives ``p'(s)``.
        d2: ``(B, S, 3)`` second derivatives ``p''(s)``.
        eps: threshold in radians per unit ``s``.

    Returns:
        ``(B, S)`` bool, True where the Frenet frame is undefined.
    """
    _check_pair(d1, d2)
    cross = torch.linalg.cross(d1, d2, dim=-1)
    return (cross * cross).sum(-1) <= (eps * (d1 * d1).sum(-1)) ** 2


def frenet_frames(d1: torch.Tensor, d2: torch.Tensor, eps: float = FRENET_EPS) -> Frames:
    """Frenet-Serret frames as in the paper: ``T = p'/|p'|``, ``B = p' x p'' / |p' x p''|``, ``N = B x T``.

    Args:
        d1: ``(B, S, 3)`` first derivatives ``p'(s)``.
        d2: ``(B, S, 3)`` second derivatives ``p''(s)``.
        eps: radians per unit ``s`` below which the frame counts as undefined (see ``frenet_degenerate``).

    Returns:
        ``Frames`` with ``(B, S, 3)`` fields.

    Raises:
        ShapeError: where the frame is undefined (a straight segment or an inflection); use
            ``rotation_minimizing_frames`` there. Never returns NaN.
    """
    check_positive(eps, "eps")
    degenerate = frenet_degenerate(d1, d2, eps)
    if bool(degenerate.any()):
        b, i = (int(v) for v in torch.nonzero(degenerate)[0])
        raise ShapeError(
            f"Frenet frame undefined: |p' x p''| ~ 0 (straight segment or inflection) at curve {b}, sample {i} "
            f"({int(degenerate.sum())} of {degenerate.numel()} samples); use rotation-minimising frames ('rmf')"
        )
    tangent = unit(d1)
    binormal = unit(torch.linalg.cross(d1, d2, dim=-1))
    normal = torch.linalg.cross(binormal, tangent, dim=-1)
    return Frames(tangent, normal, binormal)


def initial_normal(d1: torch.Tensor, d2: torch.Tensor, eps: float = FRENET_EPS) -> torch.Tensor:
    """A deterministic unit normal at the start of each curve, to seed ``rotation_minimizing_frames``.

    The Frenet normal ``(p' x p'') x p'`` (normalised) where it is defined (see ``frenet_degenerate``); else the
    coordinate axis least aligned with the tangent (first such axis on ties), made perpendicular to the tangent.
    The choice switches where the curvature crosses ``eps``; for a tube of circular section this only rolls the
    vertex ordering around the tube, not the surface.

    Args:
        d1: ``(B, 3)`` first derivative ``p'`` at the start.
        d2: ``(B, 3)`` second derivative ``p''`` at the start.
        eps: radians per unit ``s`` below which the Frenet normal counts as undefined.

    Returns:
        ``(B, 3)`` unit normals, perpendicular to ``d1``.
    """
    check_shape(d1, ("B", 3), "d1")
    check_shape(d2, ("B", 3), "d2")
    tangent = unit(d1)
    degenerate = frenet_degenerate(d1[:, None], d2[:, None], eps)[:, 0]  # (B,)
    frenet = torch.linalg.cross(torch.linalg.cross(d1, d2, dim=-1), d1, dim=-1)  # (B, 3), along N
    axis_index = torch.argmin(tangent.abs(), dim=-1)  # (B,)
    axis = torch.nn.functional.one_hot(axis_index, 3).to(tangent.dtype)  # (B, 3)
    fallback = axis - (axis * tangent).sum(-1, keepdim=True) * tangent  # |fallback| >= sqrt(2/3)
    return unit(torch.where(degenerate[:, None], fallback, frenet))


def rotation_minimizing_frames(
    points: torch.Tensor, tangents: torch.Tensor, normal_start: torch.Tensor
) -> Frames:
    """Rotation-minimising frames by the double-reflection method (Wang, Juettler, Zheng, Liu 2008).

    Defined everywhere (straight segments, inflections): each step reflects the frame in the plane bisecting the
    chord ``x_{i+1} - x_i``, then in the plane that maps the reflected tangent onto ``t_{i+1}``. A reflection is
    skipped (identity) where its plane is undefined (coincident points, a tangent reversal), so values and
    gradients stay finite.

    On CPU (float32 or float64, outside ``torch.compile``) the loop and its reverse pass run in numba kernels
    (``pipeline.shapes._rmf_numba``, in float64: about 0.1 ms a call forward and backward for the shape fit's
    batches of 1-8 curves of 32 samples, against 1.3-1.9 ms as torch operations); elsewhere as torch operations
    (``_rmf_torch``: the steps' reflections chained by a prefix product, ``torch.where`` with safe denominators).
    Both give the step-by-step loop's normals (tests).

    Args:
        points: ``(B, S, 3)`` curve samples, in order along the curve, ``S >= 1``.
        tangents: ``(B, S, 3)`` tangents at the samples (any positive length; normalised here). A zero tangent
            gives a zero tangent and binormal at that sample (finite, but not a frame).
        normal_start: ``(B, 3)`` normal at the first sample (need not be unit or exactly perpendicular; it is
            projected and normalised), e.g. from ``initial_normal``.

    Returns:
        ``Frames`` with ``(B, S, 3)`` fields; the normal of sample 0 is ``normal_start`` made orthonormal.
    """
    dims = check_shape(points, ("B", "S", 3), "points")
    check_shape(tangents, (dims["B"], dims["S"], 3), "tangents")
    check_shape(normal_start, (dims["B"], 3), "normal_start")
    if numba_path(points) and tangents.dtype == points.dtype == normal_start.dtype:
        return Frames(*RotationMinimizingFrames.apply(points, tangents, normal_start))
    return _rmf_torch(points, tangents, normal_start)


def _rmf_torch(points: torch.Tensor, tangents: torch.Tensor, normal_start: torch.Tensor) -> Frames:
    """``rotation_minimizing_frames`` as torch operations (any device; inputs checked by the caller)."""
    t = unit(tangents)
    r = _orthonormalise(normal_start, t[:, 0])  # (B, 3)
    # Step i maps r_i to r_{i+1} = H(v2_i) H(v1_i) r_i with Householder reflections H(v) = I - 2 v v^T / (v.v)
    # whose planes do not depend on r, so all steps are built at once and chained by a prefix product.
    v1 = points[:, 1:] - points[:, :-1]  # (B, S-1, 3) chords
    v2 = t[:, 1:] - _reflect(t[:, :-1], v1)  # (B, S-1, 3)
    steps = _matmul3(_householder(v2), _householder(v1))  # (B, S-1, 3, 3)
    # Not a loop of double reflections over the samples: same normals to 1e-15, 6x slower (B 4, S 100, one thread).
    prefix = steps  # Hillis-Steele inclusive scan: prefix[:, i] = steps[:, i] @ ... @ steps[:, 0]
    shift = 1
    while shift < prefix.shape[1]:
        prefix = torch.cat([prefix[:, :shift], _matmul3(prefix[:, shift:], prefix[:, :-shift])], dim=1)
        shift *= 2
    rest = (prefix * r[:, None, None, :]).sum(-1)  # (B, S-1, 3) = prefix @ r
    normals = torch.cat([r[:, None], rest], dim=1)  # (B, S, 3)
    normal = _orthonormalise(normals, t)  # removes rounding drift only
    binormal = torch.linalg.cross(t, normal, dim=-1)
    return Frames(t, normal, binormal)


def bezier_frames(
    control_points: torch.Tensor | Sequence[torch.Tensor], s: torch.Tensor, method: str = "rmf"
) -> tuple[torch.Tensor, Frames]:
    """Points and frames of Bezier centrelines.

    On CPU (float32 or float64, outside ``torch.compile``) the rotation-minimising frames come from one compiled
    call per control-point tensor, forward and backward (``_rmf_numba.BezierRotationMinimizingFrames``, float64
    inside): the torch operations of the points, derivatives, start normal and frames (``_bezier_frames_torch``,
    used elsewhere and for Frenet frames) were a fifth of a shape-fit step's time. Both give the same values and
    gradients to float rounding (tests).

    Args:
        control_points: ``(B, n+1, 3)`` control points (camera frame, metres), ``n >= 1``; or a sequence of such
            tensors, each of its own order ``n``: their curves come out in one batch, in turn (``B`` the sum of
            their batch sizes), so curves of different orders share the frames' and every later step's operations.
        s: ``(S,)`` increasing curve parameters in [0, 1].
        method: ``"rmf"`` (rotation-minimising, seeded by ``initial_normal``; defined everywhere) or
            ``"frenet"`` (the paper's; raises ``ShapeError`` on straight parts and inflections).

    Returns:
        ``(points (B, S, 3), Frames)``.
    """
    check_choice(method, FRAME_METHODS, "frame method")
    groups = [control_points] if isinstance(control_points, torch.Tensor) else list(control_points)
    if not groups:
        raise ShapeError("control_points: expected a tensor or a non-empty sequence of tensors, got an empty one")
    if method == "rmf" and all(_numba_frames(c, s) for c in groups):
        key = tuple(s.tolist())
        parts = [BezierRotationMinimizingFrames.apply(c, bezier_weights(_order(c), key), FRENET_EPS) for c in groups]
        points, *frames = parts[0] if len(parts) == 1 else (torch.cat(column) for column in zip(*parts))
        return points, Frames(*frames)
    return _bezier_frames_torch(groups, s, method)


def _bezier_frames_torch(groups: list[torch.Tensor], s: torch.Tensor, method: str) -> tuple[torch.Tensor, Frames]:
    """``bezier_frames`` of a non-empty list of control-point tensors as torch operations (any device)."""
    parts = [(bezier_points(c, s), bezier_derivative(c, s, 1), bezier_derivative(c, s, 2)) for c in groups]
    points, d1, d2 = parts[0] if len(parts) == 1 else (torch.cat(column) for column in zip(*parts))
    # Where p' = 0 (coincident end control points) the tangent's limit is along p''.
    d1 = torch.where((d1 * d1).sum(-1, keepdim=True) > 0, d1, d2)
    if method == "frenet":
        return points, frenet_frames(d1, d2)
    return points, rotation_minimizing_frames(points, d1, initial_normal(d1[:, 0], d2[:, 0]))


def _numba_frames(control_points: torch.Tensor, s: torch.Tensor) -> bool:
    """Whether ``bezier_frames`` takes the compiled path for these control points (checked as the torch path
    checks them): CPU float32 or float64, ``s`` alike, outside ``torch.compile``."""
    _order(control_points)
    _check_s(s, control_points)
    return numba_path(control_points) and not s.requires_grad


@functools.lru_cache(maxsize=64)
def bezier_weights(n: int, s: tuple[float, ...]) -> np.ndarray:
    """``(3, S, n+1)`` float64 weights of the control points in a Bezier curve's point, first and second
    derivative at the parameters ``s``: row 0 the Bernstein basis ``b_{i,n}(s)``, row 1 ``n (b_{i-1,n-1} -
    b_{i,n-1})``, row 2 ``n (n-1) (b_{i-2,n-2} - 2 b_{i-1,n-2} + b_{i,n-2})`` (``bezier_derivative``'s forward
    differences written as weights; zero for ``n < 2``)."""
    t = torch.tensor(s, dtype=torch.float64)
    weights = np.zeros((3, len(s), n + 1))
    weights[0] = bernstein_basis(n, t).numpy()
    for k in (1, 2):
        if k > n:
            break
        difference = np.eye(n + 1)
        for _ in range(k):
            difference = difference[1:] - difference[:-1]  # (n+1-k, n+1): the k-th forward differences
        weights[k] = math.perm(n, k) * bernstein_basis(n - k, t).numpy() @ difference
    weights.setflags(write=False)  # cached: shared by every call with these arguments
    return weights


def _check_pair(d1: torch.Tensor, d2: torch.Tensor) -> None:
    dims = check_shape(d1, ("B", "S", 3), "d1")
    check_shape(d2, (dims["B"], dims["S"], 3), "d2")


# Not torch.nn.functional.normalize: its gradient at v = 0 is 1 / eps (1e12), this one's is 0.
def unit(v: torch.Tensor) -> torch.Tensor:
    """``v / |v|`` along the last axis; 0 (with gradient 0) where ``v = 0`` instead of NaN."""
    sq = (v * v).sum(-1, keepdim=True)
    nonzero = sq > 0
    inv = torch.where(nonzero, torch.rsqrt(torch.where(nonzero, sq, torch.ones_like(sq))), torch.zeros_like(sq))
    return v * inv


def _reflect(x: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Reflect ``x`` in the plane through 0 with normal ``v``: ``x - 2 (v.x) v / (v.v)``; identity where ``v ~ 0``."""
    c = (v * v).sum(-1, keepdim=True)
    tiny = torch.finfo(v.dtype).tiny ** 0.5
    defined = c > tiny
    factor = torch.where(defined, 2.0 / torch.where(defined, c, torch.ones_like(c)), torch.zeros_like(c))
    return x - factor * (v * x).sum(-1, keepdim=True) * v


def _householder(v: torch.Tensor) -> torch.Tensor:
    """``(..., 3, 3)`` matrices of ``_reflect`` in the planes with normals ``v`` ``(..., 3)``; identity at ``v ~ 0``."""
    c = (v * v).sum(-1, keepdim=True)
    tiny = torch.finfo(v.dtype).tiny ** 0.5
    defined = c > tiny
    factor = torch.where(defined, 2.0 / torch.where(defined, c, torch.ones_like(c)), torch.zeros_like(c))
    eye = torch.eye(3, dtype=v.dtype, device=v.device)
    return eye - factor[..., None] * v[..., :, None] * v[..., None, :]


def _matmul3(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``a @ b`` for batches of 3x3 matrices, as broadcast products (torch's small batched matmul is slow on CPU)."""
    return (a[..., :, :, None] * b[..., None, :, :]).sum(-2)


def _orthonormalise(n: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """Unit part of ``n`` perpendicular to unit ``t`` (both ``(..., 3)``)."""
    return unit(n - (n * t).sum(-1, keepdim=True) * t)
