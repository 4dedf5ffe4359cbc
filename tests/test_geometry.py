import math

import cv2
import numpy as np
import pytest
import torch

from pipeline.errors import ShapeError
from pipeline.geometry import (
    invert_transform,
    make_transform,
    rot6d_to_rotmat,
    rotation_angle_between,
    rotmat_to_rot6d,
    rotmat_to_rotvec,
    rotvec_to_rotmat,
    transform_points,
)


def random_rotvecs(B, seed, max_angle=math.pi):
    g = torch.Generator().manual_seed(seed)
    axis = torch.nn.functional.normalize(torch.randn(B, 3, generator=g, dtype=torch.float64), dim=-1)
    angle = max_angle * torch.rand(B, 1, generator=g, dtype=torch.float64)
    return axis * angle


def random_transforms(B, seed):
    g = torch.Generator().manual_seed(seed + 100)
    t = torch.randn(B, 3, generator=g, dtype=torch.float64)
    return make_transform(rotvec_to_rotmat(random_rotvecs(B, seed)), t)


def rodrigues(rotvec):
    return torch.from_numpy(np.stack([cv2.Rodrigues(r.detach().numpy())[0] for r in rotvec]))


# --- rotation vectors ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("B", [1, 5])
def test_rotvec_to_rotmat_matches_opencv(B):
    rotvec = random_rotvecs(B, B)
    R = rotvec_to_rotmat(rotvec)
    assert R.shape == (B, 3, 3)
    torch.testing.assert_close(R, rodrigues(rotvec))


def test_rotvec_small_and_half_turn_angles_match_opencv():
    axis = torch.nn.functional.normalize(torch.tensor([[0.3, -0.5, 0.8]], dtype=torch.float64), dim=-1)
    rotvec = torch.cat([axis * a for a in (0.0, 1e-9, 1e-4, 1e-2, math.pi - 1e-6, math.pi)])
    torch.testing.assert_close(rotvec_to_rotmat(rotvec), rodrigues(rotvec))
    back = rotmat_to_rotvec(rodrigues(rotvec))
    ref = torch.from_numpy(np.stack([cv2.Rodrigues(R)[0][:, 0] for R in rodrigues(rotvec).numpy()]))
    torch.testing.assert_close(back[:-1], ref[:-1])
    # at exactly pi the axis sign is arbitrary
    torch.testing.assert_close(back[-1].abs(), ref[-1].abs())


@pytest.mark.parametrize("B", [1, 4])
def test_rotmat_to_rotvec_matches_opencv(B):
    rotvec = random_rotvecs(B, 10 + B, max_angle=3.0)
    back = rotmat_to_rotvec(rodrigues(rotvec))
    assert back.shape == (B, 3)
    torch.testing.assert_close(back, rotvec)


def test_rotvec_gradient_at_zero_is_finite():
    rotvec = torch.zeros(2, 3, dtype=torch.float64, requires_grad=True)
    (grad,) = torch.autograd.grad(rotvec_to_rotmat(rotvec)[:, 1, 0].sum(), rotvec)
    torch.testing.assert_close(grad, torch.tensor([[0.0, 0.0, 1.0]] * 2, dtype=torch.float64))  # dR10/drz = 1
    (grad,) = torch.autograd.grad(rotmat_to_rotvec(rotvec_to_rotmat(rotvec)).sum(), rotvec)
    torch.testing.assert_close(grad, torch.ones(2, 3, dtype=torch.float64))


def test_rotvec_gradcheck():
    rotvec = torch.cat([random_rotvecs(3, 7, max_angle=2.5), torch.tensor([[1e-5, -2e-5, 0.0]], dtype=torch.float64)])
    assert torch.autograd.gradcheck(rotvec_to_rotmat, (rotvec.requires_grad_(),))
    R = rotvec_to_rotmat(random_rotvecs(3, 8, max_angle=2.5)).requires_grad_()
    assert torch.autograd.gradcheck(rotmat_to_rotvec, (R,))


def test_rotation_invalid_shapes():
    with pytest.raises(ShapeError, match=r"rotvec: expected shape \(B, 3\), got \(3,\)"):
        rotvec_to_rotmat(torch.zeros(3))
    with pytest.raises(ShapeError, match=r"R: expected shape \(B, 3, 3\)"):
        rotmat_to_rotvec(torch.eye(3))
    with pytest.raises(ShapeError, match=r"rot6d: expected shape \(B, 6\)"):
        rot6d_to_rotmat(torch.zeros(2, 9))


# --- 6D -----------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("B", [1, 6])
def test_rot6d_roundtrip(B):
    R = rodrigues(random_rotvecs(B, 20 + B))
    rot6d = rotmat_to_rot6d(R)
    assert rot6d.shape == (B, 6)
    torch.testing.assert_close(rot6d[:, :3], R[:, :, 0])  # first column first
    torch.testing.assert_close(rot6d_to_rotmat(rot6d), R)


def test_rot6d_orthonormalises():
    g = torch.Generator().manual_seed(0)
    R = rot6d_to_rotmat(torch.randn(8, 6, generator=g, dtype=torch.float64))
    eye = torch.eye(3, dtype=torch.float64).expand(8, 3, 3)
    torch.testing.assert_close(R.transpose(-1, -2) @ R, eye)
    torch.testing.assert_close(torch.linalg.det(R), torch.ones(8, dtype=torch.float64))


def test_rot6d_gradcheck():
    rot6d = torch.randn(3, 6, generator=torch.Generator().manual_seed(1), dtype=torch.float64).requires_grad_()
    assert torch.autograd.gradcheck(rot6d_to_rotmat, (rot6d,))


# --- transforms ---------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("B", [1, 3])
def test_transform_points_matches_opencv(B):
    rotvec = random_rotvecs(B, 30 + B)
    t = torch.randn(B, 3, generator=torch.Generator().manual_seed(B), dtype=torch.float64)
    T = make_transform(rotvec_to_rotmat(rotvec), t)
    assert T.shape == (B, 4, 4)
    torch.testing.assert_close(T[:, 3], torch.tensor([0, 0, 0, 1.0], dtype=torch.float64).expand(B, 4))
    points = torch.randn(B, 7, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    out = transform_points(T, points)
    assert out.shape == (B, 7, 3)
    for b in range(B):
        ref = cv2.transform(points[b].numpy()[None], T[b, :3].numpy())[0]
        np.testing.assert_allclose(out[b].numpy(), ref, atol=1e-12)


@pytest.mark.parametrize("B", [1, 4])
def test_invert_transform(B):
    T = random_transforms(B, B)
    eye = torch.eye(4, dtype=torch.float64).expand(B, 4, 4)
    torch.testing.assert_close(invert_transform(T) @ T, eye)
    torch.testing.assert_close(invert_transform(T), torch.linalg.inv(T))


def test_transform_invalid():
    with pytest.raises(ShapeError, match=r"t: expected shape \(2, 3\), got \(1, 3\)"):
        make_transform(torch.eye(3).expand(2, 3, 3), torch.zeros(1, 3))
    with pytest.raises(ShapeError, match=r"points: expected shape \(1, \*, 3\), got \(2, 5, 3\)"):
        transform_points(torch.eye(4)[None], torch.zeros(2, 5, 3))
    with pytest.raises(ShapeError, match=r"T: expected shape \(B, 4, 4\)"):
        invert_transform(torch.eye(4))


def test_transform_gradcheck():
    R = rodrigues(random_rotvecs(2, 3)).requires_grad_()
    t = torch.randn(2, 3, dtype=torch.float64, requires_grad=True)
    points = torch.randn(2, 4, 3, dtype=torch.float64, requires_grad=True)
    def fn(R, t, p):
        return transform_points(invert_transform(make_transform(R, t)), p)

    assert torch.autograd.gradcheck(fn, (R, t, points))


# --- angles -------------------------------------------------------------------------------------------------------


def test_rotation_angle_between_values():
    axis = torch.nn.functional.normalize(torch.tensor([[1.0, 2.0, -0.5]], dtype=torch.float64), dim=-1)
    angles = torch.tensor([0.0, 1e-9, 1e-6, 0.3, 2.0, math.pi - 1e-7, math.pi], dtype=torch.float64)
    R1 = rodrigues(random_rotvecs(len(angles), 40))
    R2 = R1 @ rodrigues(axis * angles[:, None])
    got = rotation_angle_between(R1, R2)
    assert got.shape == (len(angles),)
    torch.testing.assert_close(got, angles, atol=1e-12, rtol=1e-6)
    torch.testing.assert_close(rotation_angle_between(R2, R1), got)


def test_rotation_angle_between_gradients():
    eye = torch.eye(3, dtype=torch.float64).expand(2, 3, 3)
    R = torch.stack([torch.eye(3, dtype=torch.float64), rodrigues(torch.tensor([[0.0, 0.0, math.pi]]).double())[0]])
    R.requires_grad_()
    (grad,) = torch.autograd.grad(rotation_angle_between(eye, R).sum(), R)
    assert torch.isfinite(grad).all()
    rotvec = torch.zeros(1, 3, dtype=torch.float64, requires_grad=True)
    (grad,) = torch.autograd.grad(rotation_angle_between(eye[:1], rotvec_to_rotmat(rotvec)).sum(), rotvec)
    assert torch.isfinite(grad).all()
    R1 = rodrigues(random_rotvecs(3, 50)).requires_grad_()
    R2 = rodrigues(random_rotvecs(3, 51)).requires_grad_()
    assert torch.autograd.gradcheck(rotation_angle_between, (R1, R2))
