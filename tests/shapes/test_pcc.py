import math

import numpy as np
import pytest
import torch

from pipeline.errors import ShapeError
from pipeline.shapes.pcc import bend_to_curvature_plane, pcc_points_frames, pcc_section_fractions
from pipeline.shapes.polyline import resample_polyline
from pipeline.synth.soft_arm import pcc_centerline


def _identity_base(B, dtype=torch.float64):
    return torch.zeros(B, 3, dtype=dtype), torch.eye(3, dtype=dtype).expand(B, 3, 3)


@pytest.mark.parametrize("B", [1, 3])
def test_points_match_the_synthetic_integrator(B):
    # pipeline.synth.soft_arm.pcc_centerline integrates the arcs by 400 exact chord steps per section (a frame
    # product, not our closed form) and
    # rotates about (cos p, sin p, 0): the same arm as the bend vector kappa L (sin p, -cos p).
    g = np.random.default_rng(B)
    for b in range(B):
        kappa, planes, lengths = g.uniform(0, 15, 3), g.uniform(0, 2 * math.pi, 3), g.uniform(0.03, 0.1, 3)
        reference = pcc_centerline(list(kappa), list(planes), list(lengths), 201)
        bends = torch.tensor([[[k * L * math.sin(p), -k * L * math.cos(p)] for k, p, L in zip(kappa, planes, lengths)]],
                             dtype=torch.float64)
        # 400 samples per section: the same vertices as the reference's chords (resampling error cancels)
        points, frames = pcc_points_frames(*_identity_base(1), bends, torch.from_numpy(lengths[None]), 400)
        assert points.shape == (1, 3 * 400 + 1, 3)
        np.testing.assert_allclose(resample_polyline(points[0].numpy(), 201), reference, atol=1e-9)


def test_frames_are_orthonormal_and_follow_the_tangent():
    g = torch.Generator().manual_seed(0)
    bends = torch.randn(2, 3, 2, generator=g, dtype=torch.float64)
    R = torch.linalg.qr(torch.randn(2, 3, 3, generator=g, dtype=torch.float64))[0]
    R = R * torch.sign(torch.linalg.det(R))[:, None, None]  # proper rotations
    base = torch.randn(2, 3, generator=g, dtype=torch.float64)
    points, frames = pcc_points_frames(base, R, bends, torch.full((2, 3), 0.07, dtype=torch.float64), 200)
    torch.testing.assert_close(points[:, 0], base)
    torch.testing.assert_close(frames.tangent[:, 0], R[..., 2])
    F = torch.stack(frames, dim=-1)  # (B, P, 3, 3) columns T, N, B
    eye = torch.eye(3, dtype=torch.float64).expand_as(F)
    torch.testing.assert_close(F.transpose(-1, -2) @ F, eye)
    torch.testing.assert_close(torch.linalg.cross(frames.tangent, frames.normal, dim=-1), frames.binormal)
    chord = points[:, 1:] - points[:, :-1]  # the chord direction is the mean of the end tangents on an arc
    mean = frames.tangent[:, 1:] + frames.tangent[:, :-1]
    cosine = (chord * mean).sum(-1) / (chord.norm(dim=-1) * mean.norm(dim=-1))
    assert float(cosine.min()) > 1 - 1e-9
    step = chord.norm(dim=-1)  # arc length per step: each section's length over m (the chords are slightly shorter)
    assert float((step.sum(-1) - 0.21).abs().max()) < 1e-4


def test_straight_sections_are_straight_and_finite():
    bends = torch.zeros(1, 2, 2, dtype=torch.float64)
    points, frames = pcc_points_frames(*_identity_base(1), bends, torch.tensor([[0.1, 0.05]], dtype=torch.float64), 5)
    expected = torch.zeros(11, 3, dtype=torch.float64)
    expected[:6, 2] = torch.linspace(0, 0.1, 6, dtype=torch.float64)
    expected[6:, 2] = 0.1 + torch.linspace(0.01, 0.05, 5, dtype=torch.float64)
    torch.testing.assert_close(points[0], expected)
    assert torch.isfinite(torch.stack(frames)).all()


@pytest.mark.parametrize("scale", [0.0, 1e-7, 3e-3, 0.5])
def test_gradcheck_through_and_near_straight(scale):
    # Exactly straight, near straight (Taylor branch) and bent: gradients of points and frames against finite
    # differences, and no NaN at 0.
    g = torch.Generator().manual_seed(1)
    bends = (scale * torch.randn(1, 2, 2, generator=g, dtype=torch.float64)).requires_grad_(True)
    lengths = torch.tensor([[0.1, 0.08]], dtype=torch.float64, requires_grad=True)
    base = torch.randn(1, 3, generator=g, dtype=torch.float64, requires_grad=True)
    R = torch.linalg.qr(torch.randn(1, 3, 3, generator=g, dtype=torch.float64))[0].requires_grad_(True)

    def f(base, R, bends, lengths):
        points, frames = pcc_points_frames(base, R, bends, lengths, 3)
        return points, frames.tangent, frames.normal

    assert torch.autograd.gradcheck(f, (base, R, bends, lengths), eps=1e-6, atol=1e-6)
    out = sum(o.sum() for o in f(base, R, bends, lengths))
    (grad,) = torch.autograd.grad(out, bends)
    assert torch.isfinite(grad).all()


def test_taylor_branch_meets_the_exact_formula():
    # On both sides of the switch (a^2 = 1e-4) the points agree to rounding.
    for a in (0.00999999, 0.01000001):
        bends = torch.tensor([[[a, 0.0]]], dtype=torch.float64)
        points, _ = pcc_points_frames(*_identity_base(1), bends, torch.tensor([[0.1]], dtype=torch.float64), 1)
        kappa = a / 0.1
        expected = torch.tensor([(1 - math.cos(a)) / kappa, 0.0, math.sin(a) / kappa], dtype=torch.float64)
        torch.testing.assert_close(points[0, -1], expected, atol=1e-15, rtol=1e-12)


def test_fractions_curvature_plane_and_errors():
    fractions = pcc_section_fractions(torch.tensor([[0.05, 0.15]]), 2)
    torch.testing.assert_close(fractions, torch.tensor([[0.0, 0.125, 0.25, 0.625, 1.0]]))
    kappa, plane = bend_to_curvature_plane(torch.tensor([[0.0, 1.0], [0.0, 0.0]]), torch.tensor([0.1, 0.1]))
    torch.testing.assert_close(kappa, torch.tensor([10.0, 0.0]))
    torch.testing.assert_close(plane, torch.tensor([math.pi / 2, 0.0]))
    base, R = _identity_base(1)
    with pytest.raises(ShapeError, match="bends"):
        pcc_points_frames(base, R, torch.zeros(1, 2, 3), torch.ones(1, 2), 4)
    with pytest.raises(ShapeError, match="samples_per_section"):
        pcc_points_frames(base, R, torch.zeros(1, 2, 2, dtype=torch.float64), torch.ones(1, 2), 0)
