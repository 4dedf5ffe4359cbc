"""Bezier curves of any order, batched: points and derivatives in closed form (Bernstein polynomials).

Convention: control points ``c_0..c_n`` are rows of a ``(B, n+1, D)`` tensor (``D = 3`` for a centreline in the
camera frame, metres); the curve parameter ``s`` runs over [0, 1] with ``p(0) = c_0`` and ``p(1) = c_n``.
Derivatives are taken with respect to ``s`` (units: metres per unit ``s``).
"""

from __future__ import annotations

import math

import torch

from pipeline.checks import check_shape
from pipeline.errors import ConfigError, ShapeError

__all__ = ["bernstein_basis", "bezier_points", "bezier_derivative", "elevate_bezier_degree"]


def bernstein_basis(n: int, s: torch.Tensor) -> torch.Tensor:
    """Bernstein polynomials ``b_{i,n}(s) = binom(n, i) (1-s)^(n-i) s^i`` for ``i = 0..n``.

    Args:
        n: polynomial degree, ``n >= 0``.
        s: ``(S,)`` curve parameters in [0, 1] (values outside extrapolate).

    Returns:
        ``(S, n+1)`` basis values, dtype and device of ``s``.
    """
    if isinstance(n, bool) or not isinstance(n, int) or n < 0:
        raise ConfigError(f"Bernstein degree: expected an int >= 0, got {n!r}")
    check_shape(s, ("S",), "s")
    i = torch.arange(n + 1, dtype=s.dtype, device=s.device)  # (n+1,)
    binom = torch.tensor([math.comb(n, k) for k in range(n + 1)], dtype=s.dtype, device=s.device)
    s_col = s[:, None]  # (S, 1), broadcasts against (n+1,)
    # torch.pow with exponent 0 has gradient 0 (not 0 * inf), so s = 0 and s = 1 are gradient-safe.
    return binom * torch.pow(1.0 - s_col, n - i) * torch.pow(s_col, i)


def bezier_points(control_points: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
    """Points ``p(s) = sum_i b_{i,n}(s) c_i`` of Bezier curves.

    Args:
        control_points: ``(B, n+1, D)`` control points, ``n >= 1`` (camera frame, metres for a centreline).
        s: ``(S,)`` curve parameters in [0, 1].

    Returns:
        ``(B, S, D)`` points on the curves.
    """
    n = _order(control_points)
    _check_s(s, control_points)
    basis = bernstein_basis(n, s)  # (S, n+1)
    return torch.einsum("sk,bkd->bsd", basis, control_points)


def bezier_derivative(control_points: torch.Tensor, s: torch.Tensor, order: int = 1) -> torch.Tensor:
    """``order``-th derivative ``d^k p / ds^k`` of Bezier curves, in closed form.

    ``p^(k)(s) = n! / (n-k)! * sum_{i=0}^{n-k} b_{i,n-k}(s) Delta^k c_i`` with forward differences
    ``Delta c_i = c_{i+1} - c_i``; zero when ``k > n``. For the quadratic (``n = 2``) this is
    ``p' = 2(1-s)(c1-c0) + 2s(c2-c1)`` and ``p'' = 2(c2 - 2c1 + c0)``.

    Args:
        control_points: ``(B, n+1, D)`` control points, ``n >= 1``.
        s: ``(S,)`` curve parameters in [0, 1].
        order: derivative order ``k >= 1``.

    Returns:
        ``(B, S, D)`` derivatives (units of the control points per unit ``s``^k).
    """
    n = _order(control_points)
    _check_s(s, control_points)
    if isinstance(order, bool) or not isinstance(order, int) or order < 1:
        raise ConfigError(f"derivative order: expected an int >= 1, got {order!r}")
    B, _, D = control_points.shape
    if order > n:
        # Zero, but still a function of the inputs, so autograd returns zero gradients rather than failing.
        return (0.0 * control_points[:, :1]).expand(B, s.shape[0], D)
    diffs = control_points
    for _ in range(order):
        diffs = diffs[:, 1:] - diffs[:, :-1]  # (B, n+1-k, D) after k passes
    scale = math.perm(n, order)  # n! / (n-k)!
    basis = bernstein_basis(n - order, s)  # (S, n-k+1)
    return scale * torch.einsum("sk,bkd->bsd", basis, diffs)


def elevate_bezier_degree(control_points: torch.Tensor, degrees: int = 1) -> torch.Tensor:
    """The same curves written with ``degrees`` more control points (exact degree elevation).

    One step: ``c'_i = (i / (n+1)) c_{i-1} + (1 - i / (n+1)) c_i`` for ``i = 0..n+1`` (with ``c_{-1}`` and
    ``c_{n+1}`` taken as zero; their weights are zero), so ``p'(s) = p(s)`` for every ``s``. Each new control point
    is a convex combination of old ones (it stays in their convex hull, e.g. in front of the camera).

    Args:
        control_points: ``(B, n+1, D)`` control points, ``n >= 1``.
        degrees: how many orders to add, ``>= 0``.

    Returns:
        ``(B, n+1+degrees, D)`` control points, dtype and device of the input.
    """
    _order(control_points)
    if isinstance(degrees, bool) or not isinstance(degrees, int) or degrees < 0:
        raise ConfigError(f"degrees: expected an int >= 0, got {degrees!r}")
    out = control_points
    for _ in range(degrees):
        m = out.shape[1]  # n + 1
        w = torch.arange(1, m, dtype=out.dtype, device=out.device)[None, :, None] / m  # (1, n, 1): i / (n+1)
        middle = w * out[:, :-1] + (1.0 - w) * out[:, 1:]  # (B, n, D), i = 1..n
        out = torch.cat([out[:, :1], middle, out[:, -1:]], dim=1)
    return out


def _order(control_points: torch.Tensor) -> int:
    check_shape(control_points, ("B", None, None), "control_points")
    if control_points.shape[1] < 2:
        raise ShapeError(
            f"control_points: expected (B, n+1, D) with n >= 1 (at least 2 control points), "
            f"got {tuple(control_points.shape)}"
        )
    if not control_points.is_floating_point():
        raise ShapeError(f"control_points: expected a floating-point tensor, got {control_points.dtype}")
    return control_points.shape[1] - 1


def _check_s(s: torch.Tensor, control_points: torch.Tensor) -> None:
    check_shape(s, ("S",), "s")
    if s.dtype != control_points.dtype or s.device != control_points.device:
        raise ShapeError(
            f"s: expected dtype {control_points.dtype} on {control_points.device} like control_points, "
            f"got {s.dtype} on {s.device}"
        )
