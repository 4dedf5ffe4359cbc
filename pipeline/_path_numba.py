"""CPU model path points: a tube's projected path at fractions of its visible length, and their gradient, as one
compiled call each way (``shape_estimation._FitProblem.model_keypoints`` uses it for CPU tensors).

In tensor operations (``shape_estimation._path_points_torch``) the caps' outer edges, the path's segment lengths,
their running sum, the search for each fraction and the interpolation are about 250 small operations forward and
as many autograd nodes backward: 1.4 ms a call for one tube, a fifth of a single-start shape-fit step, where the
arithmetic is a few microseconds. Here each curve is a loop in float64; the backward pass walks it in reverse (the
derivatives are written out in the comments). Same values and gradients as the tensor operations to float
rounding (tests), and the same conventions: a zero-length span takes its far end, a clamped interpolation
parameter passes no gradient, the farthest ring vertex alone moves a cap's edge.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np
import torch
from torch.autograd.function import once_differentiable

_JIT = dict(cache=True, nogil=True, fastmath=False)

CAP_EPS = 1e-12  # added to a direction's squared length before its inverse square root (``_cap_edge``)
LENGTH_EPS = 1e-12  # added to a segment's squared length before its square root


@nb.njit(**_JIT)
def _cap(end, previous, ring, out):
    """``shape_estimation._cap_edge`` of one curve: ``end`` moved along the unit direction ``end - previous`` to the
    farthest vertex of ``ring`` (A, 2) in that direction (not moved when none lies beyond); returns the index of
    that vertex, or -1 when the edge did not move."""
    dx = end[0] - previous[0]
    dy = end[1] - previous[1]
    inv = 1.0 / math.sqrt(dx * dx + dy * dy + CAP_EPS)
    dx *= inv
    dy *= inv
    best = -1
    reach = 0.0
    for a in range(ring.shape[0]):
        r = (ring[a, 0] - end[0]) * dx + (ring[a, 1] - end[1]) * dy
        if best < 0 or r > reach:
            best = a
            reach = r
    if reach < 0.0:
        reach = 0.0
        best = -1
    out[0] = end[0] + reach * dx
    out[1] = end[1] + reach * dy
    return best


@nb.njit(**_JIT)
def _cap_back(end, previous, ring, best, g_out, g_end, g_previous, g_ring):
    """Reverse of ``_cap``: adds ``dL/d end``, ``dL/d previous`` and ``dL/d ring`` from ``g_out``. With ``d = end -
    previous``, ``n = d / sqrt(d.d + eps)``, ``reach = (ring[best] - end).n`` (0 when ``best < 0``):
    ``out = end + reach n``, so ``dL/dreach = g.n``, ``dL/dn = reach g + dL/dreach (ring[best] - end)`` and
    ``dL/dd = (dL/dn - (dL/dn . n) n) / sqrt(d.d + eps)`` (the ``eps`` kept in ``n``'s length: ``n.n < 1``)."""
    dx = end[0] - previous[0]
    dy = end[1] - previous[1]
    q = dx * dx + dy * dy + CAP_EPS
    inv = 1.0 / math.sqrt(q)
    nx = dx * inv
    ny = dy * inv
    g_end[0] += g_out[0]
    g_end[1] += g_out[1]
    gnx = 0.0
    gny = 0.0
    if best >= 0:
        rx = ring[best, 0] - end[0]
        ry = ring[best, 1] - end[1]
        reach = rx * nx + ry * ny
        g_reach = g_out[0] * nx + g_out[1] * ny
        gnx = reach * g_out[0] + g_reach * rx
        gny = reach * g_out[1] + g_reach * ry
        g_ring[best, 0] += g_reach * nx
        g_ring[best, 1] += g_reach * ny
        g_end[0] -= g_reach * nx
        g_end[1] -= g_reach * ny
    # n = d q^(-1/2): dn/dd = (I - d d^T / q) / sqrt(q)
    dg = (dx * gnx + dy * gny) / q
    gdx = (gnx - dg * dx) * inv
    gdy = (gny - dg * dy) * inv
    g_end[0] += gdx
    g_end[1] += gdy
    g_previous[0] -= gdx
    g_previous[1] -= gdy


@nb.njit(**_JIT)
def path_forward(centre, rings, bounds, fractions, attributes, path, cum, visible, caps, lower, t, clamped, located,
                 located_attributes):
    """Fill, per curve: ``path (S, R+2, 2)`` (the base cap's edge, the ring centres ``centre (S, R, 2)``, the tip
    cap's edge; ``rings (S, 2, A, 2)`` the end rings' projected vertices), ``caps (S, 2)`` (``_cap``'s vertex
    indices), ``visible (S, R+1)`` (segments whose middle lies within ``bounds`` = u_min, v_min, u_max, v_max),
    ``cum (S, R+2)`` (running visible length), and at each of ``fractions (K,)`` of the visible length the segment
    ``lower (S, K)``, its parameter ``t (S, K)`` (``clamped`` True where it passes no gradient), ``located (S, K,
    2)`` and ``located_attributes (S, K, C)`` (``attributes (S, R, C)`` at the same places; the cap edges take the
    end rings' values)."""
    S, R = centre.shape[0], centre.shape[1]
    K = fractions.shape[0]
    C = attributes.shape[2]
    for s in range(S):
        caps[s, 0] = _cap(centre[s, 0], centre[s, 1], rings[s, 0], path[s, 0])
        caps[s, 1] = _cap(centre[s, R - 1], centre[s, R - 2], rings[s, 1], path[s, R + 1])
        for i in range(R):
            path[s, i + 1, 0] = centre[s, i, 0]
            path[s, i + 1, 1] = centre[s, i, 1]
        cum[s, 0] = 0.0
        for i in range(R + 1):
            dx = path[s, i + 1, 0] - path[s, i, 0]
            dy = path[s, i + 1, 1] - path[s, i, 1]
            mu = 0.5 * (path[s, i + 1, 0] + path[s, i, 0])
            mv = 0.5 * (path[s, i + 1, 1] + path[s, i, 1])
            visible[s, i] = bounds[0] <= mu <= bounds[2] and bounds[1] <= mv <= bounds[3]
            length = math.sqrt(dx * dx + dy * dy + LENGTH_EPS)
            cum[s, i + 1] = cum[s, i] + (length if visible[s, i] else 0.0)
        total = cum[s, R + 1]
        for k in range(K):
            target = fractions[k] * total
            upper = 0  # torch.searchsorted(side="left"): the first index whose running length is >= target
            while upper < R + 2 and cum[s, upper] < target:
                upper += 1
            upper = min(max(upper, 1), R + 1)
            lo = upper - 1
            lower[s, k] = lo
            span = cum[s, upper] - cum[s, lo]
            if span > 0.0:
                x = (target - cum[s, lo]) / span
                clamped[s, k] = x < 0.0 or x > 1.0
                tk = min(max(x, 0.0), 1.0)
            else:
                clamped[s, k] = True
                tk = 1.0
            t[s, k] = tk
            for j in range(2):
                located[s, k, j] = path[s, lo, j] + tk * (path[s, upper, j] - path[s, lo, j])
            a0 = min(max(lo - 1, 0), R - 1)  # padded attributes: index i of the path is ring i - 1, clipped
            a1 = min(max(upper - 1, 0), R - 1)
            for c in range(C):
                located_attributes[s, k, c] = attributes[s, a0, c] + tk * (attributes[s, a1, c] - attributes[s, a0, c])


@nb.njit(**_JIT)
def path_backward(centre, rings, fractions, attributes, path, cum, visible, caps, lower, t, clamped, g_located,
                  g_attributes):
    """``(dL/d centre (S, R, 2), dL/d rings (S, 2, A, 2), dL/d attributes (S, R, C))`` from the gradients of
    ``path_forward``'s ``located`` and ``located_attributes``. With ``x = (target - c_l) / (c_u - c_l)`` and
    ``target = f c_last``: ``dx/dtarget = 1 / span``, ``dx/dc_l = (x - 1) / span``, ``dx/dc_u = -x / span``; the
    running length passes ``dL/dc_j`` to every visible segment before ``j``; a segment's length ``sqrt(d.d +
    eps)`` passes ``dL/dlength d / length`` to its end and minus that to its start."""
    S, R = centre.shape[0], centre.shape[1]
    K = fractions.shape[0]
    C = attributes.shape[2]
    g_centre = np.zeros(centre.shape)
    g_rings = np.zeros(rings.shape)
    g_attr = np.zeros(attributes.shape)
    g_path = np.zeros((R + 2, 2))
    g_cum = np.zeros(R + 2)
    for s in range(S):
        g_path[:] = 0.0
        g_cum[:] = 0.0
        total = cum[s, R + 1]
        for k in range(K):
            lo = lower[s, k]
            up = lo + 1
            tk = t[s, k]
            g_t = 0.0
            for j in range(2):
                g = g_located[s, k, j]
                g_path[lo, j] += (1.0 - tk) * g
                g_path[up, j] += tk * g
                g_t += g * (path[s, up, j] - path[s, lo, j])
            a0 = min(max(lo - 1, 0), R - 1)
            a1 = min(max(up - 1, 0), R - 1)
            for c in range(C):
                g = g_attributes[s, k, c]
                g_attr[s, a0, c] += (1.0 - tk) * g
                g_attr[s, a1, c] += tk * g
                g_t += g * (attributes[s, a1, c] - attributes[s, a0, c])
            if not clamped[s, k]:
                span = cum[s, up] - cum[s, lo]
                x = (fractions[k] * total - cum[s, lo]) / span
                g_cum[R + 1] += fractions[k] * g_t / span
                g_cum[lo] += g_t * (x - 1.0) / span
                g_cum[up] -= g_t * x / span
        running = 0.0  # dL/d(length of segment i) = sum of dL/dc_j over j > i, for a visible segment
        for i in range(R, -1, -1):
            running += g_cum[i + 1]
            if visible[s, i]:
                dx = path[s, i + 1, 0] - path[s, i, 0]
                dy = path[s, i + 1, 1] - path[s, i, 1]
                inv = 1.0 / math.sqrt(dx * dx + dy * dy + LENGTH_EPS)
                g_path[i + 1, 0] += running * dx * inv
                g_path[i + 1, 1] += running * dy * inv
                g_path[i, 0] -= running * dx * inv
                g_path[i, 1] -= running * dy * inv
        for i in range(R):
            g_centre[s, i, 0] += g_path[i + 1, 0]
            g_centre[s, i, 1] += g_path[i + 1, 1]
        _cap_back(centre[s, 0], centre[s, 1], rings[s, 0], caps[s, 0], g_path[0], g_centre[s, 0], g_centre[s, 1],
                  g_rings[s, 0])
        _cap_back(centre[s, R - 1], centre[s, R - 2], rings[s, 1], caps[s, 1], g_path[R + 1], g_centre[s, R - 1],
                  g_centre[s, R - 2], g_rings[s, 1])
    return g_centre, g_rings, g_attr


class PathPoints(torch.autograd.Function):
    """``(centre (S, R, 2), rings (S, 2, A, 2), attributes (S, R, C), bounds (4,) array, fractions (K,) array)``
    -> ``(located (S, K, 2), located attributes (S, K, C))``: ``path_forward`` in float64, returned in the dtype of
    ``centre``; differentiable in ``centre``, ``rings`` and ``attributes``."""

    @staticmethod
    def forward(ctx, centre, rings, attributes, bounds, fractions):
        dtype = centre.dtype
        c = centre.detach().to(torch.float64).contiguous().numpy()
        r = rings.detach().to(torch.float64).contiguous().numpy()
        a = attributes.detach().to(torch.float64).contiguous().numpy()
        S, R = c.shape[0], c.shape[1]
        K, C = fractions.shape[0], a.shape[2]
        path = np.empty((S, R + 2, 2))
        cum = np.empty((S, R + 2))
        visible = np.empty((S, R + 1), np.bool_)
        caps = np.empty((S, 2), np.int64)
        lower = np.empty((S, K), np.int64)
        t = np.empty((S, K))
        clamped = np.empty((S, K), np.bool_)
        located = np.empty((S, K, 2))
        located_attributes = np.empty((S, K, C))
        path_forward(c, r, bounds, fractions, a, path, cum, visible, caps, lower, t, clamped, located,
                     located_attributes)
        ctx.saved = (c, r, fractions, a, path, cum, visible, caps, lower, t, clamped)
        return torch.from_numpy(located).to(dtype), torch.from_numpy(located_attributes).to(attributes.dtype)

    @staticmethod
    @once_differentiable
    def backward(ctx, g_located, g_attributes):
        c, r, fractions, a, path, cum, visible, caps, lower, t, clamped = ctx.saved
        K = fractions.shape[0]

        def as_array(grad, shape):
            return np.zeros(shape) if grad is None else grad.detach().to(torch.float64).contiguous().numpy()

        g_centre, g_rings, g_attr = path_backward(
            c, r, fractions, a, path, cum, visible, caps, lower, t, clamped,
            as_array(g_located, (c.shape[0], K, 2)), as_array(g_attributes, (c.shape[0], K, a.shape[2])))
        dtype = g_located.dtype if g_located is not None else g_attributes.dtype
        return (torch.from_numpy(g_centre).to(dtype), torch.from_numpy(g_rings).to(dtype),
                torch.from_numpy(g_attr).to(dtype), None, None)
