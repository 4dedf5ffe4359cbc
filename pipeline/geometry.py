"""Rotations and rigid transforms as batch-first tensor functions (differentiable, device and dtype from inputs).

Convention:
    Rotation matrices act on column vectors (``p' = R @ p``), right-handed, radians. A rotation vector is the unit
    axis times the angle. Transforms are ``(B, 4, 4)`` homogeneous matrices named ``T_<to>_<from>``:
    ``p_cam = T_cam_root @ p_root``.
"""

from __future__ import annotations

import torch
from kornia.geometry.conversions import axis_angle_to_rotation_matrix, rotation_matrix_to_axis_angle

from pipeline.checks import check_shape


def rotvec_to_rotmat(rotvec: torch.Tensor) -> torch.Tensor:
    """Rotation vectors to rotation matrices (Rodrigues' formula).

    Convention: ``rotvec = angle * axis``, radians, right-hand rule; ``R @ p`` rotates column vectors ``p``.
    Smooth at ``rotvec = 0`` (a Taylor branch below 1e-3 rad; finite gradients there).

    Args:
        rotvec: ``(B, 3)`` rotation vectors, radians.

    Returns:
        ``(B, 3, 3)`` rotation matrices.
    """
    check_shape(rotvec, ("B", 3), "rotvec")
    return axis_angle_to_rotation_matrix(rotvec)


def rotmat_to_rotvec(R: torch.Tensor) -> torch.Tensor:
    """Rotation matrices to rotation vectors with angle in ``[0, pi]``.

    Convention: inverse of :func:`rotvec_to_rotmat`; at an angle of exactly pi either axis sign may come back.
    The input is not checked for orthonormality.

    Args:
        R: ``(B, 3, 3)`` rotation matrices.

    Returns:
        ``(B, 3)`` rotation vectors, radians.
    """
    check_shape(R, ("B", 3, 3), "R")
    return rotation_matrix_to_axis_angle(R)


def rot6d_to_rotmat(rot6d: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    """6D rotation representation (Zhou et al., CVPR 2019) to rotation matrices by Gram-Schmidt.

    Convention: ``rot6d = (a1, a2)`` are the *first two columns* of ``R`` before orthonormalisation
    (``[R00, R10, R20, R01, R11, R21]``); PyTorch3D uses rows instead. ``b1 = a1 / |a1|``,
    ``b2 = (a2 - (b1 . a2) b1) / |...|``, ``b3 = b1 x b2``, ``R = [b1 b2 b3]``. Norms are clamped at ``eps``, so
    degenerate inputs (``a1 = 0`` or ``a2`` parallel to ``a1``) give a finite but meaningless result.

    Args:
        rot6d: ``(B, 6)`` two 3-vectors, unitless.

    Returns:
        ``(B, 3, 3)`` rotation matrices.
    """
    check_shape(rot6d, ("B", 6), "rot6d")
    a1, a2 = rot6d[:, :3], rot6d[:, 3:]  # (B, 3) each
    b1 = torch.nn.functional.normalize(a1, dim=-1, eps=eps)
    b2 = torch.nn.functional.normalize(a2 - (b1 * a2).sum(-1, keepdim=True) * b1, dim=-1, eps=eps)
    b3 = torch.linalg.cross(b1, b2, dim=-1)
    return torch.stack([b1, b2, b3], dim=-1)  # (B, 3, 3), the b's as columns


def rotmat_to_rot6d(R: torch.Tensor) -> torch.Tensor:
    """Rotation matrices to the 6D representation: the first two columns, ``[R00, R10, R20, R01, R11, R21]``.

    Args:
        R: ``(B, 3, 3)`` rotation matrices.

    Returns:
        ``(B, 6)``.
    """
    check_shape(R, ("B", 3, 3), "R")
    return torch.cat([R[:, :, 0], R[:, :, 1]], dim=-1)


def make_transform(R: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """Homogeneous transforms ``[[R, t], [0, 0, 0, 1]]``.

    Convention: ``T_a_b`` maps points in frame ``b`` to frame ``a``: ``p_a = R @ p_b + t``; ``t`` in metres.

    Args:
        R: ``(B, 3, 3)`` rotations.
        t: ``(B, 3)`` translations, metres.

    Returns:
        ``(B, 4, 4)`` transforms.
    """
    dims = check_shape(R, ("B", 3, 3), "R")
    check_shape(t, (dims["B"], 3), "t")
    top = torch.cat([R, t[:, :, None]], dim=-1)  # (B, 3, 4)
    bottom = torch.zeros_like(top[:, :1, :])  # (B, 1, 4)
    bottom[:, 0, 3] = 1.0
    return torch.cat([top, bottom], dim=-2)


def invert_transform(T: torch.Tensor) -> torch.Tensor:
    """Inverse of rigid transforms: ``T_b_a`` from ``T_a_b``, as ``[[R^T, -R^T t], [0, 1]]``.

    Args:
        T: ``(B, 4, 4)`` rigid transforms (the rotation block is assumed orthonormal).

    Returns:
        ``(B, 4, 4)``.
    """
    check_shape(T, ("B", 4, 4), "T")
    R_inv = T[:, :3, :3].transpose(-1, -2)  # (B, 3, 3)
    t_inv = -(R_inv @ T[:, :3, 3:4])[:, :, 0]  # (B, 3)
    return make_transform(R_inv, t_inv)


def transform_points(T: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Apply rigid transforms to point sets: ``p_a = R @ p_b + t``.

    Args:
        T: ``(B, 4, 4)`` transforms ``T_a_b``.
        points: ``(B, N, 3)`` points in frame ``b``, metres.

    Returns:
        ``(B, N, 3)`` points in frame ``a``.
    """
    dims = check_shape(T, ("B", 4, 4), "T")
    check_shape(points, (dims["B"], None, 3), "points")
    return points @ T[:, :3, :3].transpose(-1, -2) + T[:, None, :3, 3]  # (B, N, 3)


def rotation_angle_between(R1: torch.Tensor, R2: torch.Tensor) -> torch.Tensor:
    """Geodesic angle of ``R1^T R2``, in ``[0, pi]`` radians.

    Computed as ``atan2(|vee(R - R^T)| / 2, (trace(R) - 1) / 2)`` with ``R = R1^T R2``, which is accurate near 0
    and near pi (unlike ``acos`` of the trace). The gradient is finite everywhere; at angle 0 and pi, where the
    angle is not differentiable, it is the zero sub-gradient of the ``sin`` part.

    Args:
        R1: ``(B, 3, 3)`` rotations.
        R2: ``(B, 3, 3)`` rotations.

    Returns:
        ``(B,)`` angles, radians.
    """
    dims = check_shape(R1, ("B", 3, 3), "R1")
    check_shape(R2, (dims["B"], 3, 3), "R2")
    R = R1.transpose(-1, -2) @ R2  # (B, 3, 3)
    axis2 = torch.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], dim=-1)  # (B, 3)
    sq = (axis2 * axis2).sum(-1)  # (B,) = (2 sin(angle))^2
    positive = sq > 0
    safe_sq = torch.where(positive, sq, torch.ones_like(sq))  # sqrt never sees 0, so its backward stays finite
    sin_angle = torch.where(positive, torch.sqrt(safe_sq), torch.zeros_like(sq)) / 2
    cos_angle = (R.diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2
    return torch.atan2(sin_angle, cos_angle)
