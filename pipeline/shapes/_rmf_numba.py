"""CPU rotation-minimising frames: the double-reflection loop and its reverse pass as numba kernels behind a torch
autograd Function (``rotation_minimizing_frames`` uses it for CPU tensors).

The torch version (``frames._rmf_torch``, used on other devices) builds every step's reflections and chains them
by a prefix product: about 150 small tensor operations forward and as many autograd nodes backward, 1.3-1.9 ms a
call for the shape fit's 1-8 curves of 32 samples, where the arithmetic is a few microseconds. Here one call does
the loop in float64 and the backward pass walks it in reverse (the derivatives are written out in the kernels'
comments); same values to float rounding, and the same conventions: a reflection whose plane is undefined
(``v.v <= tiny``, ``tiny`` the input dtype's ``finfo.tiny ** 0.5``) is skipped, a zero vector normalises to zero
with a zero gradient.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np
import torch
from torch.autograd.function import once_differentiable

_JIT = dict(cache=True, nogil=True, fastmath=False)


@nb.njit(inline="always", **_JIT)
def _dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


@nb.njit(inline="always", **_JIT)
def _reflect(a, v, c, tiny, out):
    """``out = a - 2 (v.a) v / c`` (``c = v.v``); ``out = a`` where ``c <= tiny``."""
    k = 2.0 / c if c > tiny else 0.0
    s = k * _dot(v, a)
    for j in range(3):
        out[j] = a[j] - s * v[j]


@nb.njit(inline="always", **_JIT)
def _reflect_back(a, v, c, tiny, gy, ga, gv):
    """Reverse of ``_reflect``: with ``y = a - k s v``, ``k = 2 / c``, ``s = v.a``, ``c = v.v`` and ``gy = dL/dy``:
    ``dL/da = gy - k (gy.v) v`` and ``dL/dv = (2 k s (gy.v) / c) v - k (gy.v) a - k s gy``; written (not added) to
    ``ga`` and ``gv``; ``ga = gy``, ``gv = 0`` where the reflection was skipped."""
    if c > tiny:
        k = 2.0 / c
        s = _dot(v, a)
        gyv = _dot(gy, v)
        for j in range(3):
            ga[j] = gy[j] - k * gyv * v[j]
            gv[j] = 2.0 * k * s * gyv / c * v[j] - k * gyv * a[j] - k * s * gy[j]
    else:
        for j in range(3):
            ga[j] = gy[j]
            gv[j] = 0.0


@nb.njit(inline="always", **_JIT)
def _orthonormalise_back(a, t, y, gy, ga, gt, u, gu):
    """Reverse of ``y = unit(u)``, ``u = a - (a.t) t``: writes ``dL/da`` to ``ga`` and adds ``dL/dt`` to ``gt``
    (``gy = dL/dy``; ``u``, ``gu`` scratch). ``dL/du = (gy - (gy.y) y) / |u|`` (0 where ``u = 0``); ``du/da = I -
    t t^T``; ``du`` along ``dt`` is ``-(a.dt) t - (a.t) dt``."""
    p = _dot(a, t)
    for j in range(3):
        u[j] = a[j] - p * t[j]
    norm = math.sqrt(_dot(u, u))
    q = _dot(gy, y)
    for j in range(3):
        gu[j] = (gy[j] - q * y[j]) / norm if norm > 0.0 else 0.0
    tg = _dot(t, gu)
    for j in range(3):
        ga[j] = gu[j] - tg * t[j]
        gt[j] += -tg * a[j] - p * gu[j]


@nb.njit(inline="always", **_JIT)
def _step(x, t, r, b, i, tiny, v1, v2, left, t_left):
    """Step ``i`` of curve ``b`` up to its second reflection: writes the chord ``v1 = x_{i+1} - x_i``, ``left =
    H(v1) r_i``, ``t_left = H(v1) t_i`` and ``v2 = t_{i+1} - t_left``; returns ``(v1.v1, v2.v2)``."""
    for j in range(3):
        v1[j] = x[b, i + 1, j] - x[b, i, j]
    c1 = _dot(v1, v1)
    _reflect(r[b, i], v1, c1, tiny, left)
    _reflect(t[b, i], v1, c1, tiny, t_left)
    for j in range(3):
        v2[j] = t[b, i + 1, j] - t_left[j]
    return c1, _dot(v2, v2)


@nb.njit(**_JIT)
def rmf_forward(x, d, n0, tiny, t, r, normal, binormal):
    """Fill ``t`` (unit tangents), ``r`` (the reflected normals before the final orthonormalisation), ``normal``
    and ``binormal`` ``(B, S, 3)`` from points ``x`` and tangents ``d`` ``(B, S, 3)`` and start normals ``n0``
    ``(B, 3)`` (float64 arrays)."""
    B, S = x.shape[0], x.shape[1]
    scratch = np.empty((4, 3))  # 3-vectors
    v1, v2, left, t_left = scratch[0], scratch[1], scratch[2], scratch[3]
    for b in range(B):
        for i in range(S):
            sq = _dot(d[b, i], d[b, i])
            inv = 1.0 / math.sqrt(sq) if sq > 0.0 else 0.0
            for j in range(3):
                t[b, i, j] = d[b, i, j] * inv
        # r_0 = unit(n0 - (n0.t_0) t_0)
        p = _dot(n0[b], t[b, 0])
        for j in range(3):
            left[j] = n0[b, j] - p * t[b, 0, j]
        sq = _dot(left, left)
        inv = 1.0 / math.sqrt(sq) if sq > 0.0 else 0.0
        for j in range(3):
            r[b, 0, j] = left[j] * inv
        for i in range(S - 1):  # r_{i+1} = H(v2) H(v1) r_i
            _, c2 = _step(x, t, r, b, i, tiny, v1, v2, left, t_left)
            _reflect(left, v2, c2, tiny, r[b, i + 1])
        for i in range(S):  # normal = unit(r - (r.t) t), binormal = t x normal
            p = _dot(r[b, i], t[b, i])
            for j in range(3):
                left[j] = r[b, i, j] - p * t[b, i, j]
            sq = _dot(left, left)
            inv = 1.0 / math.sqrt(sq) if sq > 0.0 else 0.0
            for j in range(3):
                normal[b, i, j] = left[j] * inv
            tt, nn = t[b, i], normal[b, i]
            binormal[b, i, 0] = tt[1] * nn[2] - tt[2] * nn[1]
            binormal[b, i, 1] = tt[2] * nn[0] - tt[0] * nn[2]
            binormal[b, i, 2] = tt[0] * nn[1] - tt[1] * nn[0]


@nb.njit(**_JIT)
def rmf_backward(x, d, n0, tiny, t, r, normal, g_t, g_normal, g_binormal):
    """Gradients ``(dL/dx, dL/dd (B, S, 3), dL/dn0 (B, 3))`` from those of the outputs ``(B, S, 3)``; ``t``, ``r``,
    ``normal`` as ``rmf_forward`` filled them."""
    B, S = x.shape[0], x.shape[1]
    gx = np.zeros((B, S, 3))
    gd = np.zeros((B, S, 3))
    gn0 = np.zeros((B, 3))
    gt = np.empty((S, 3))
    gr = np.zeros((S, 3))
    scratch = np.empty((13, 3))  # 3-vectors
    gn, gu, u, v1, v2 = scratch[0], scratch[1], scratch[2], scratch[3], scratch[4]
    left, t_left, g_left, g_t_left = scratch[5], scratch[6], scratch[7], scratch[8]
    g_v2, g_v1a, g_v1b, g_a = scratch[9], scratch[10], scratch[11], scratch[12]
    for b in range(B):
        for i in range(S):
            tt, nn, gb = t[b, i], normal[b, i], g_binormal[b, i]
            # binormal = t x normal: dL/dt += normal x gb, dL/dnormal += gb x t
            gt[i, 0] = g_t[b, i, 0] + nn[1] * gb[2] - nn[2] * gb[1]
            gt[i, 1] = g_t[b, i, 1] + nn[2] * gb[0] - nn[0] * gb[2]
            gt[i, 2] = g_t[b, i, 2] + nn[0] * gb[1] - nn[1] * gb[0]
            gn[0] = g_normal[b, i, 0] + gb[1] * tt[2] - gb[2] * tt[1]
            gn[1] = g_normal[b, i, 1] + gb[2] * tt[0] - gb[0] * tt[2]
            gn[2] = g_normal[b, i, 2] + gb[0] * tt[1] - gb[1] * tt[0]
            _orthonormalise_back(r[b, i], tt, nn, gn, gr[i], gt[i], u, gu)  # normal = unit(r - (r.t) t)
        for i in range(S - 2, -1, -1):  # the loop in reverse: gr[i + 1] is complete here
            c1, c2 = _step(x, t, r, b, i, tiny, v1, v2, left, t_left)
            _reflect_back(left, v2, c2, tiny, gr[i + 1], g_left, g_v2)
            for j in range(3):
                gt[i + 1, j] += g_v2[j]
                g_t_left[j] = -g_v2[j]
            _reflect_back(r[b, i], v1, c1, tiny, g_left, g_a, g_v1a)
            for j in range(3):
                gr[i, j] += g_a[j]
            _reflect_back(t[b, i], v1, c1, tiny, g_t_left, g_a, g_v1b)
            for j in range(3):
                gt[i, j] += g_a[j]
                gx[b, i + 1, j] += g_v1a[j] + g_v1b[j]
                gx[b, i, j] -= g_v1a[j] + g_v1b[j]
        _orthonormalise_back(n0[b], t[b, 0], r[b, 0], gr[0], gn0[b], gt[0], u, gu)  # r_0 = unit(n0 - (n0.t_0) t_0)
        for i in range(S):  # t = d / |d|
            sq = _dot(d[b, i], d[b, i])
            if sq > 0.0:
                q = _dot(gt[i], t[b, i])
                inv = 1.0 / math.sqrt(sq)
                for j in range(3):
                    gd[b, i, j] = (gt[i, j] - q * t[b, i, j]) * inv
    return gx, gd, gn0


class RotationMinimizingFrames(torch.autograd.Function):
    """``(points, tangents (B, S, 3), normal_start (B, 3))`` -> ``(tangent, normal, binormal)`` ``(B, S, 3)``
    (``frames.rotation_minimizing_frames``), computed in float64, returned in the inputs' dtype."""

    @staticmethod
    def forward(ctx, points, tangents, normal_start):
        dtype = points.dtype
        tiny = float(torch.finfo(dtype).tiny) ** 0.5
        x = points.detach().to(torch.float64).contiguous().numpy()
        d = tangents.detach().to(torch.float64).contiguous().numpy()
        n0 = normal_start.detach().to(torch.float64).contiguous().numpy()
        t, r, normal, binormal = (np.empty(x.shape) for _ in range(4))
        rmf_forward(x, d, n0, tiny, t, r, normal, binormal)
        ctx.saved = (x, d, n0, tiny, t, r, normal)
        return tuple(torch.from_numpy(a).to(dtype) for a in (t, normal, binormal))

    @staticmethod
    @once_differentiable
    def backward(ctx, g_t, g_normal, g_binormal):
        x, d, n0, tiny, t, r, normal = ctx.saved
        dtype = g_t.dtype if g_t is not None else g_normal.dtype if g_normal is not None else g_binormal.dtype

        def as_array(grad):
            return np.zeros(x.shape) if grad is None else grad.detach().to(torch.float64).contiguous().numpy()

        gx, gd, gn0 = rmf_backward(x, d, n0, tiny, t, r, normal, as_array(g_t), as_array(g_normal),
                                   as_array(g_binormal))
        return tuple(torch.from_numpy(a).to(dtype) for a in (gx, gd, gn0))
