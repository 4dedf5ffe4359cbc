"""Rotations and rigid transforms as batch-first tensor functions (differentiable, device and dtype from inputs).

Convention:
    Rotation matrices act on column vectors (``p' = R @ p``), right-handed, radians. A rotation vector is the unit
    axis times the angle. Transforms are ``(B, 4, 4)`` homogeneous matrices named ``T_<to>_<from>``:
    ``p_cam = T_cam_root @ p_root``.

Build and invert transforms with kornia (``Rt_to_matrix4x4``, ``inverse_transformation``); 6D rotations with
``pytorch_kinematics.rotation_6d_to_matrix``.
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
