"""CPU rendered ring radii: ``shape_estimation._FitProblem.render_radii`` and its gradient as one compiled call each
way (it uses this for CPU tensors).

In tensor operations (``shape_estimation._render_radii_torch``) the arc-length fractions, the radius profile's
interpolation, the soft edge's offset (a table looked up at each ring's apparent radius and spacing) and the
shrink are about 230 small operations forward and a hundred autograd nodes backward: 0.6-0.9 ms a call, a sixth of
a single-start shape-fit step. Here each curve is a loop in float64; the backward pass walks it in reverse (the
derivatives in the comments). Same values and gradients as the tensor operations to float rounding (tests), and
the same conventions: the edge offset passes no gradient, a clamped fraction passes none, ``max(a, b)`` splits a
tie's gradient in half.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np
import torch
from torch.autograd.function import once_differentiable

_JIT = dict(cache=True, nogil=True, fastmath=False)

STEP_EPS = 1e-18  # added to a step's squared length before its square root (``arc_length_fractions``)
MIN_DEPTH_M = 1e-9  # the edge offset's depth floor (``_FitProblem.edge_offsets``)
FLOOR = 0.1  # a rendered radius is at least this fraction of the ring's radius


@nb.njit(inline="always", **_JIT)
def _unit_interval(q):
    """``q`` clamped to [0, 1], NaN to 0 (so that no index taken from it leaves the profile)."""
    if not q >= 0.0:
        return 0.0
    return q if q <= 1.0 else 1.0


@nb.njit(inline="always", **_JIT)
def _locate(value, bounds, logs):
    """``_EdgeOffsets._locate`` of one value: the knot interval ``upper`` and the parameter in it, in log units."""
    n = logs.shape[0]
    x = math.log(min(max(value, bounds[0]), bounds[n - 1]))
    upper = 0
    while upper < n and logs[upper] < x:  # torch.searchsorted(side="left")
        upper += 1
    upper = min(max(upper, 1), n - 1)
    return upper, (x - logs[upper - 1]) / (logs[upper] - logs[upper - 1])


@nb.njit(**_JIT)
def radii_forward(points, profile, rim, focal, scale, table, radius_bounds, radius_logs, spacing_bounds,
                  spacing_logs, out, offsets, circle, fractions):
    """Fill ``out (S, R)`` (rendered radii, metres), ``offsets (S, R)`` (the soft edge's offset less the rim's,
    working pixels), ``circle (S, R)`` (the radius profile ``(S, n)`` at each ring's fraction of arc length) and
    ``fractions (S, R)`` from ring centres ``points (S, R, 3)``; ``rim (S,)`` the rim offsets, ``table (I, J)`` the
    edge offsets at the knots' radii and spacings."""
    S, R = points.shape[0], points.shape[1]
    n = profile.shape[1]
    centre = np.empty((R, 2))
    gaps = np.empty(R - 1)
    for s in range(S):
        fractions[s, 0] = 0.0
        for i in range(R - 1):
            dx = points[s, i + 1, 0] - points[s, i, 0]
            dy = points[s, i + 1, 1] - points[s, i, 1]
            dz = points[s, i + 1, 2] - points[s, i, 2]
            fractions[s, i + 1] = fractions[s, i] + math.sqrt(dx * dx + dy * dy + dz * dz + STEP_EPS)
        total = fractions[s, R - 1]
        for i in range(R):
            fractions[s, i] /= total
            x = _unit_interval(fractions[s, i]) * (n - 1)
            lower = min(max(int(math.floor(x)), 0), n - 2)
            t = x - lower
            circle[s, i] = profile[s, lower] * (1.0 - t) + profile[s, lower + 1] * t
            depth = max(points[s, i, 2], MIN_DEPTH_M)
            centre[i, 0] = points[s, i, 0] / depth * focal
            centre[i, 1] = points[s, i, 1] / depth * focal
        for i in range(R - 1):
            gaps[i] = math.sqrt((centre[i + 1, 0] - centre[i, 0]) ** 2 + (centre[i + 1, 1] - centre[i, 1]) ** 2)
        for i in range(R):
            if i == 0:
                spacing = gaps[0]
            elif i == R - 1:
                spacing = gaps[R - 2]
            else:
                spacing = 0.5 * (gaps[i] + gaps[i - 1])
            apparent = circle[s, i] * focal / max(points[s, i, 2], MIN_DEPTH_M)
            a, t = _locate(apparent, radius_bounds, radius_logs)
            b, u = _locate(spacing, spacing_bounds, spacing_logs)
            low = table[a - 1, b - 1] * (1.0 - u) + table[a - 1, b] * u
            high = table[a, b - 1] * (1.0 - u) + table[a, b] * u
            offsets[s, i] = low + t * (high - low) - rim[s]
            shrunk = circle[s, i] * scale - offsets[s, i] * points[s, i, 2] / focal
            out[s, i] = max(shrunk, FLOOR * circle[s, i])


@nb.njit(**_JIT)
def radii_backward(points, profile, focal, scale, offsets, circle, fractions, g_out):
    """``(dL/d points (S, R, 3), dL/d profile (S, n))`` from ``g_out = dL/d out (S, R)``. With ``out = max(c scale
    - o z / f, 0.1 c)``, ``c = p_l (1 - t) + p_{l+1} t``, ``t = clamp(q, 0, 1) (n - 1) - l`` and ``q_i = cum_i /
    cum_last``: ``dL/dq_i = dL/dt (n - 1)`` inside [0, 1]; ``dL/dcum_i += dL/dq_i / cum_last``, ``dL/dcum_last -=
    sum_i dL/dq_i cum_i / cum_last^2``; a step's length passes ``dL/dlength d / length`` to its end."""
    S, R = points.shape[0], points.shape[1]
    n = profile.shape[1]
    g_points = np.zeros(points.shape)
    g_profile = np.zeros(profile.shape)
    g_cum = np.zeros(R)
    for s in range(S):
        total = 0.0  # cum_last, from the fractions: cum_i = q_i cum_last
        for i in range(R - 1):
            dx = points[s, i + 1, 0] - points[s, i, 0]
            dy = points[s, i + 1, 1] - points[s, i, 1]
            dz = points[s, i + 1, 2] - points[s, i, 2]
            total += math.sqrt(dx * dx + dy * dy + dz * dz + STEP_EPS)
        g_total = 0.0
        for i in range(R):
            g = g_out[s, i]
            shrunk = circle[s, i] * scale - offsets[s, i] * points[s, i, 2] / focal
            floor = FLOOR * circle[s, i]
            g_shrunk = g if shrunk > floor else (0.5 * g if shrunk == floor else 0.0)
            g_floor = g - g_shrunk
            g_circle = g_shrunk * scale + g_floor * FLOOR
            g_points[s, i, 2] -= g_shrunk * offsets[s, i] / focal
            q = fractions[s, i]
            x = _unit_interval(q) * (n - 1)
            lower = min(max(int(math.floor(x)), 0), n - 2)
            t = x - lower
            g_profile[s, lower] += (1.0 - t) * g_circle
            g_profile[s, lower + 1] += t * g_circle
            g_q = g_circle * (profile[s, lower + 1] - profile[s, lower]) * (n - 1) if 0.0 <= q <= 1.0 else 0.0
            g_cum[i] = g_q / total
            g_total -= g_q * q / total  # cum_i / cum_last^2 = q_i / cum_last
        g_cum[R - 1] += g_total
        running = 0.0  # dL/d(length of step i) = sum of dL/dcum_j over j > i
        for i in range(R - 2, -1, -1):
            running += g_cum[i + 1]
            dx = points[s, i + 1, 0] - points[s, i, 0]
            dy = points[s, i + 1, 1] - points[s, i, 1]
            dz = points[s, i + 1, 2] - points[s, i, 2]
            inv = running / math.sqrt(dx * dx + dy * dy + dz * dz + STEP_EPS)
            g_points[s, i + 1, 0] += dx * inv
            g_points[s, i + 1, 1] += dy * inv
            g_points[s, i + 1, 2] += dz * inv
            g_points[s, i, 0] -= dx * inv
            g_points[s, i, 1] -= dy * inv
            g_points[s, i, 2] -= dz * inv
    return g_points, g_profile


class RenderRadii(torch.autograd.Function):
    """``(points (S, R, 3), profile (S, n), rim (S,) array, focal, scale, table (I, J) array, radius knots (I,),
    spacing knots (J,))`` -> ``(rendered radii (S, R), offsets (S, R))``: ``radii_forward`` in float64, returned in
    the dtype of ``points``; the radii differentiable in ``points`` and ``profile``, the offsets constant."""

    @staticmethod
    def forward(ctx, points, profile, rim, focal, scale, table, radius_knots, spacing_knots):
        dtype = points.dtype
        x = points.detach().to(torch.float64).contiguous().numpy()
        p = profile.detach().to(torch.float64).contiguous().numpy()
        S, R = x.shape[0], x.shape[1]
        out, offsets, circle, fractions = (np.empty((S, R)) for _ in range(4))
        radii_forward(x, p, rim, float(focal), float(scale), table, radius_knots, np.log(radius_knots),
                      spacing_knots, np.log(spacing_knots), out, offsets, circle, fractions)
        ctx.saved = (x, p, float(focal), float(scale), offsets, circle, fractions)
        offsets_tensor = torch.from_numpy(offsets).to(dtype)
        ctx.mark_non_differentiable(offsets_tensor)
        return torch.from_numpy(out).to(dtype), offsets_tensor

    @staticmethod
    @once_differentiable
    def backward(ctx, g_out, g_offsets):
        x, p, focal, scale, offsets, circle, fractions = ctx.saved
        if g_out is None:
            return (None,) * 8
        g_points, g_profile = radii_backward(x, p, focal, scale, offsets, circle, fractions,
                                             g_out.detach().to(torch.float64).contiguous().numpy())
        return (torch.from_numpy(g_points).to(g_out.dtype), torch.from_numpy(g_profile).to(g_out.dtype),
                None, None, None, None, None, None)
