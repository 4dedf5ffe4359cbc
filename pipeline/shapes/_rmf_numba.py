"""CPU rotation-minimising frames: the double-reflection loop and its reverse pass as numba kernels behind a torch
autograd Function (``rotation_minimizing_frames`` uses it for CPU tensors); and the same for Bezier centrelines
from their control points (``BezierRotationMinimizingFrames``, ``bezier_frames`` uses it for CPU tensors).

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


@nb.njit(inline="always", **_JIT)
def _cross(a, b, out):
    out[0] = a[1] * b[2] - a[2] * b[1]
    out[1] = a[2] * b[0] - a[0] * b[2]
    out[2] = a[0] * b[1] - a[1] * b[0]


@nb.njit(inline="always", **_JIT)
def _unit_back(v, y, gy, gv):
    """Reverse of ``y = v / |v|`` (``y = 0`` with a zero gradient where ``v = 0``): adds ``dL/dv`` to ``gv``."""
    norm = math.sqrt(_dot(v, v))
    if norm > 0.0:
        q = _dot(gy, y)
        for j in range(3):
            gv[j] += (gy[j] - q * y[j]) / norm


@nb.njit(inline="always", **_JIT)
def _initial_normal(a, b, eps, v, n0):
    """``frames.initial_normal`` of one curve from ``a = p'(0)``, ``b = p''(0)``: writes the unnormalised normal
    to ``v`` and the unit normal to ``n0``; returns the coordinate axis of the fallback, or -1 for the Frenet
    normal ``(a x b) x a``."""
    w = np.empty(3)
    _cross(a, b, w)
    aa = _dot(a, a)
    if _dot(w, w) <= (eps * aa) ** 2:  # frenet_degenerate: the axis least aligned with the tangent
        inv = 1.0 / math.sqrt(aa) if aa > 0.0 else 0.0
        axis = 0
        for j in range(1, 3):
            if abs(a[j] * inv) < abs(a[axis] * inv):
                axis = j
        p = a[axis] * inv  # axis . t
        for j in range(3):
            v[j] = -p * a[j] * inv
        v[axis] += 1.0
    else:
        axis = -1
        _cross(w, a, v)
    sq = _dot(v, v)
    inv = 1.0 / math.sqrt(sq) if sq > 0.0 else 0.0
    for j in range(3):
        n0[j] = v[j] * inv
    return axis


@nb.njit(**_JIT)
def bezier_rmf_forward(c, w, eps, tiny, x, d, d2, fallback, v0, n0, axes, t, r, normal, binormal):
    """Points ``x``, first and second derivatives ``d``, ``d2`` ``(B, S, 3)`` of Bezier curves with control points
    ``c`` ``(B, n+1, 3)`` from the weights ``w`` ``(3, S, n+1)`` (``bezier_weights``); where ``p' = 0`` the tangent
    is ``p''`` (``fallback`` (B, S) True); the start normals (``_initial_normal``: ``v0``, ``n0`` (B, 3), ``axes``
    (B,)); then ``rmf_forward``'s ``t``, ``r``, ``normal``, ``binormal``."""
    B, N = c.shape[0], c.shape[1]
    S = w.shape[1]
    for b in range(B):
        for i in range(S):
            for j in range(3):
                a0 = 0.0
                a1 = 0.0
                a2 = 0.0
                for k in range(N):
                    ck = c[b, k, j]
                    a0 += w[0, i, k] * ck
                    a1 += w[1, i, k] * ck
                    a2 += w[2, i, k] * ck
                x[b, i, j] = a0
                d[b, i, j] = a1
                d2[b, i, j] = a2
            fallback[b, i] = not _dot(d[b, i], d[b, i]) > 0.0
            if fallback[b, i]:
                for j in range(3):
                    d[b, i, j] = d2[b, i, j]
        axes[b] = _initial_normal(d[b, 0], d2[b, 0], eps, v0[b], n0[b])
    rmf_forward(x, d, n0, tiny, t, r, normal, binormal)


@nb.njit(**_JIT)
def bezier_rmf_backward(c, w, tiny, x, d, d2, fallback, v0, n0, axes, t, r, normal, g_x, g_t, g_normal,
                        g_binormal):
    """``dL/dc`` ``(B, n+1, 3)`` from the gradients of ``bezier_rmf_forward``'s points and frames ``(B, S, 3)``."""
    gx, gd, gn0 = rmf_backward(x, d, n0, tiny, t, r, normal, g_t, g_normal, g_binormal)
    B, N = c.shape[0], c.shape[1]
    S = w.shape[1]
    gc = np.zeros((B, N, 3))
    gd2 = np.zeros((S, 3))
    scratch = np.empty((5, 3))
    gv, ga, gw, wv, tt = scratch[0], scratch[1], scratch[2], scratch[3], scratch[4]
    for b in range(B):
        for j in range(3):
            gv[j] = 0.0
            gd2[0, j] = 0.0
        _unit_back(v0[b], n0[b], gn0[b], gv)
        a = d[b, 0]
        if axes[b] < 0:  # v = w x a, w = a x b: dL/dw = a x gv, dL/da += gv x w + b x dL/dw, dL/db = dL/dw x a
            _cross(a, d2[b, 0], wv)
            _cross(a, gv, gw)
            _cross(gv, wv, ga)
            for j in range(3):
                gd[b, 0, j] += ga[j]
            _cross(d2[b, 0], gw, ga)
            for j in range(3):
                gd[b, 0, j] += ga[j]
            _cross(gw, a, ga)
            for j in range(3):
                gd2[0, j] = ga[j]
        else:  # v = e - (e.t) t, t = unit(a): dL/dt = -(e.t) gv - (gv.t) e
            aa = _dot(a, a)
            inv = 1.0 / math.sqrt(aa) if aa > 0.0 else 0.0
            for j in range(3):
                tt[j] = a[j] * inv
            et = tt[axes[b]]
            gt_ = _dot(gv, tt)
            for j in range(3):
                ga[j] = -et * gv[j]
            ga[axes[b]] -= gt_
            for j in range(3):
                gw[j] = 0.0
            _unit_back(a, tt, ga, gw)
            for j in range(3):
                gd[b, 0, j] += gw[j]
        for i in range(S):
            for j in range(3):
                g2 = gd2[i, j] if i == 0 else 0.0
                g1 = gd[b, i, j]
                if fallback[b, i]:  # the tangent was p'': its gradient goes there
                    g2 += g1
                    g1 = 0.0
                g0 = gx[b, i, j] + g_x[b, i, j]
                for k in range(N):
                    gc[b, k, j] += w[0, i, k] * g0 + w[1, i, k] * g1 + w[2, i, k] * g2
    return gc


class BezierRotationMinimizingFrames(torch.autograd.Function):
    """``(control_points (B, n+1, 3), weights (3, S, n+1) float64 array, eps)`` -> ``(points, tangent, normal,
    binormal)`` ``(B, S, 3)``: ``frames.bezier_frames`` with rotation-minimising frames (its tangent fallback and
    ``initial_normal`` seed with ``eps``), computed in float64, returned in the input's dtype. ``weights`` rows:
    the Bernstein basis and its first and second derivatives at the samples (``frames.bezier_weights``)."""

    @staticmethod
    def forward(ctx, control_points, weights, eps):
        dtype = control_points.dtype
        tiny = float(torch.finfo(dtype).tiny) ** 0.5
        c = control_points.detach().to(torch.float64).contiguous().numpy()
        B, S = c.shape[0], weights.shape[1]
        x, d, d2, t, r, normal, binormal = (np.empty((B, S, 3)) for _ in range(7))
        fallback = np.empty((B, S), np.bool_)
        v0, n0 = np.empty((B, 3)), np.empty((B, 3))
        axes = np.empty(B, np.int64)
        bezier_rmf_forward(c, weights, float(eps), tiny, x, d, d2, fallback, v0, n0, axes, t, r, normal, binormal)
        ctx.saved = (c, weights, tiny, x, d, d2, fallback, v0, n0, axes, t, r, normal)
        return tuple(torch.from_numpy(a).to(dtype) for a in (x, t, normal, binormal))

    @staticmethod
    @once_differentiable
    def backward(ctx, g_x, g_t, g_normal, g_binormal):
        c, weights, tiny, x, d, d2, fallback, v0, n0, axes, t, r, normal = ctx.saved
        grads = [g for g in (g_x, g_t, g_normal, g_binormal) if g is not None]
        dtype = grads[0].dtype if grads else torch.float64

        def as_array(grad):
            return np.zeros(x.shape) if grad is None else grad.detach().to(torch.float64).contiguous().numpy()

        gc = bezier_rmf_backward(c, weights, tiny, x, d, d2, fallback, v0, n0, axes, t, r, normal, as_array(g_x),
                                 as_array(g_t), as_array(g_normal), as_array(g_binormal))
        return torch.from_numpy(gc).to(dtype), None, None
