"""Piecewise constant curvature (PCC) centrelines: the continuum-robotics standard model, differentiable.

Convention: camera frame (OpenCV), metres, radians. An arm of ``N`` sections starts at ``base`` with the frame
``R_base`` (columns: body x, body y, body z = the tangent leaving the base). Section ``i`` is a circular arc of
length ``L_i`` whose *bend vector* ``b_i = (b_x, b_y)`` (radians) is given in the frame the section starts in:
it bends by the angle ``|b_i|`` (the tangent turns by that much over the section; curvature
``kappa_i = |b_i| / L_i``) towards the direction ``(b_x, b_y, 0)`` of that frame (bending-plane angle
``phi_i = atan2(b_y, b_x)``, from body x towards body y). The frame is carried along the arc by the rotation about
the bending axis ``(-sin phi, cos phi, 0)`` (no twist about the tangent: the frames are rotation-minimising), and
section ``i + 1`` starts in the frame section ``i`` ends in. A straight section is ``b_i = 0``: the bend vector
has no singularity there (the plane angle is undefined but never needed), and every function below is smooth
and NaN-free through it (Taylor branches of ``sin(a)/a``, ``(1 - cos a)/a^2``, ``(a - sin a)/a^3`` below
``a^2 < 1e-4``).

Within a section, at the fraction ``t`` of its length: rotation vector ``theta(t) = t (-b_y, b_x, 0)``, frame
``R_base ... R(theta(t))`` and position ``L t J(theta(t)) e_z`` from the section's start, with ``R`` Rodrigues'
rotation and ``J`` the left Jacobian of SO(3) (the exact integral of the rotating tangent).
"""

from __future__ import annotations

import torch

from pipeline.checks import check_shape
from pipeline.errors import ShapeError
from pipeline.shapes.frames import Frames

__all__ = ["pcc_points_frames", "pcc_section_fractions", "bend_to_curvature_plane"]

#: Below this squared angle (rad^2) the Taylor branches are used (error below 1e-12 relative in float64).
_SMALL_ANGLE_SQ = 1e-4


def _coefficients(a2: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``sin(a)/a``, ``(1 - cos a)/a^2``, ``(a - sin a)/a^3`` as functions of ``a^2 >= 0``, smooth at 0."""
    small = a2 < _SMALL_ANGLE_SQ
    safe = torch.where(small, torch.ones_like(a2), a2)
    a = torch.sqrt(safe)
    sin, cos = torch.sin(a), torch.cos(a)
    c0 = torch.where(small, 1.0 - a2 / 6.0 + a2 * a2 / 120.0, sin / a)
    c1 = torch.where(small, 0.5 - a2 / 24.0 + a2 * a2 / 720.0, (1.0 - cos) / safe)
    c2 = torch.where(small, 1.0 / 6.0 - a2 / 120.0 + a2 * a2 / 5040.0, (a - sin) / (safe * a))
    return c0, c1, c2


def _arc(theta: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Rotation ``R(theta)`` ``(..., 3, 3)`` and ``J(theta) e_z`` ``(..., 3)`` of rotation vectors ``(..., 3)``
    whose z component is 0 (the bending axes of PCC sections)."""
    x, y = theta[..., 0], theta[..., 1]
    a2 = x * x + y * y
    c0, c1, c2 = _coefficients(a2)
    zero = torch.zeros_like(x)
    # [theta]x for theta = (x, y, 0); [theta]x^2 = theta theta^T - a2 I
    K = torch.stack([torch.stack([zero, zero, y], -1), torch.stack([zero, zero, -x], -1),
                     torch.stack([-y, x, zero], -1)], -2)  # (..., 3, 3)
    outer = torch.stack([torch.stack([x * x, x * y, zero], -1), torch.stack([x * y, y * y, zero], -1),
                         torch.stack([zero, zero, zero], -1)], -2)
    eye = torch.eye(3, dtype=theta.dtype, device=theta.device).expand_as(K)
    K2 = outer - a2[..., None, None] * eye
    R = eye + c0[..., None, None] * K + c1[..., None, None] * K2
    # J e_z = e_z + c1 [theta]x e_z + c2 [theta]x^2 e_z; [theta]x e_z = (y, -x, 0), [theta]x^2 e_z = (0, 0, -a2)
    Je = torch.stack([c1 * y, -c1 * x, 1.0 - c2 * a2], -1)
    return R, Je


def pcc_points_frames(
    base: torch.Tensor,
    R_base: torch.Tensor,
    bends: torch.Tensor,
    lengths: torch.Tensor,
    samples_per_section: int,
) -> tuple[torch.Tensor, Frames]:
    """Points and frames along PCC centrelines, ``samples_per_section`` evenly spaced in each section's length.

    Args:
        base: ``(B, 3)`` base point, camera frame, metres.
        R_base: ``(B, 3, 3)`` base frame (columns body x, y, z; z the tangent leaving the base), camera frame.
        bends: ``(B, N, 2)`` bend vectors ``(b_x, b_y)`` of the sections, radians (module docstring).
        lengths: ``(B, N)`` section lengths, metres (> 0).
        samples_per_section: ``m >= 1``; section ``i`` gives the points at fractions ``k / m``, ``k = 1..m``.

    Returns:
        ``(points (B, N m + 1, 3), Frames)``: the base, then each section's ``m`` points; frames with
        ``tangent`` = body z, ``normal`` = body x, ``binormal`` = body y (right-handed, rotation-minimising).
    """
    dims = check_shape(base, ("B", 3), "base")
    check_shape(R_base, (dims["B"], 3, 3), "R_base")
    N = check_shape(bends, (dims["B"], "N", 2), "bends")["N"]
    check_shape(lengths, (dims["B"], N), "lengths")
    if isinstance(samples_per_section, bool) or not isinstance(samples_per_section, int) or samples_per_section < 1:
        raise ShapeError(f"samples_per_section: expected an int >= 1, got {samples_per_section!r}")
    m = samples_per_section
    t = torch.arange(1, m + 1, dtype=bends.dtype, device=bends.device) / m  # (m,)
    frame, position = R_base, base
    points, frames = [base[:, None]], [R_base[:, None]]
    for i in range(bends.shape[1]):
        axis = torch.stack([-bends[:, i, 1], bends[:, i, 0], torch.zeros_like(bends[:, i, 0])], -1)  # (B, 3)
        R, Je = _arc(t[None, :, None] * axis[:, None, :])  # (B, m, 3, 3), (B, m, 3)
        local = (lengths[:, i, None, None] * t[None, :, None]) * Je  # (B, m, 3) from the section's start
        points.append(position[:, None] + torch.einsum("bij,bmj->bmi", frame, local))
        frames.append(torch.einsum("bij,bmjk->bmik", frame, R))
        position, frame = points[-1][:, -1], frames[-1][:, -1]
    P = torch.cat(points, dim=1)  # (B, N m + 1, 3)
    F = torch.cat(frames, dim=1)  # (B, N m + 1, 3, 3)
    return P, Frames(tangent=F[..., 2], normal=F[..., 0], binormal=F[..., 1])


def pcc_section_fractions(lengths: torch.Tensor, samples_per_section: int) -> torch.Tensor:
    """Arc-length fractions ``(B, N m + 1)`` of the points of :func:`pcc_points_frames` (0 at the base, 1 at
    the tip) for section lengths ``(B, N)``."""
    check_shape(lengths, ("B", "N"), "lengths")
    m = samples_per_section
    t = torch.arange(1, m + 1, dtype=lengths.dtype, device=lengths.device) / m  # (m,)
    start = torch.cumsum(lengths, dim=1) - lengths  # (B, N)
    along = (start[:, :, None] + lengths[:, :, None] * t).reshape(lengths.shape[0], -1)  # (B, N m)
    total = lengths.sum(dim=1, keepdim=True)
    return torch.cat([torch.zeros_like(total), along / total], dim=1)


def bend_to_curvature_plane(bends: torch.Tensor, lengths: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Curvature ``|b| / L`` (1/m) and bending-plane angle ``atan2(b_y, b_x)`` (radians, 0 for a straight
    section) of bend vectors ``(..., 2)`` over lengths ``(...)``; for reporting (not differentiable at 0)."""
    angle = torch.sqrt((bends * bends).sum(-1))
    plane = torch.where(angle > 0, torch.atan2(bends[..., 1], bends[..., 0]), torch.zeros_like(angle))
    return angle / lengths, plane
