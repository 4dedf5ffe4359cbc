import math

import cv2
import numpy as np
import pytest
import torch
from kornia.geometry.conversions import Rt_to_matrix4x4

from pipeline.errors import ShapeError
from pipeline.geometry import rotmat_to_rotvec, rotvec_to_rotmat, transform_points


def random_rotvecs(B, seed, max_angle=math.pi):
    g = torch.Generator().manual_seed(seed)
    axis = torch.nn.functional.normalize(torch.randn(B, 3, generator=g, dtype=torch.float64), dim=-1)
    angle = max_angle * torch.rand(B, 1, generator=g, dtype=torch.float64)
    return axis * angle


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


# --- transforms ---------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("B", [1, 3])
def test_transform_points_matches_opencv(B):
    rotvec = random_rotvecs(B, 30 + B)
    t = torch.randn(B, 3, generator=torch.Generator().manual_seed(B), dtype=torch.float64)
    T = Rt_to_matrix4x4(rotvec_to_rotmat(rotvec), t[:, :, None])
    assert T.shape == (B, 4, 4)
    torch.testing.assert_close(T[:, 3], torch.tensor([0, 0, 0, 1.0], dtype=torch.float64).expand(B, 4))
    points = torch.randn(B, 7, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    out = transform_points(T, points)
    assert out.shape == (B, 7, 3)
    for b in range(B):
        ref = cv2.transform(points[b].numpy()[None], T[b, :3].numpy())[0]
        np.testing.assert_allclose(out[b].numpy(), ref, atol=1e-12)


def test_transform_invalid():
    with pytest.raises(ShapeError, match=r"points: expected shape \(1, \*, 3\), got \(2, 5, 3\)"):
        transform_points(torch.eye(4)[None], torch.zeros(2, 5, 3))
    with pytest.raises(ShapeError, match=r"T: expected shape \(B, 4, 4\)"):
        transform_points(torch.eye(4), torch.zeros(1, 5, 3))


def test_transform_gradcheck():
    R = rodrigues(random_rotvecs(2, 3)).requires_grad_()
    t = torch.randn(2, 3, dtype=torch.float64, requires_grad=True)
    points = torch.randn(2, 4, 3, dtype=torch.float64, requires_grad=True)
    def fn(R, t, p):
        return transform_points(Rt_to_matrix4x4(R, t[:, :, None]), p)

    assert torch.autograd.gradcheck(fn, (R, t, points))
