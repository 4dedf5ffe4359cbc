import math

import numpy as np
import pytest
import torch
import trimesh

from pipeline.errors import ConfigError, ShapeError
from pipeline.shapes.frames import bezier_frames
from pipeline.shapes.tube import (
    bezier_tube_vertices,
    ring_parameters,
    taper_radii,
    tube_faces,
    tube_vertices,
)

F64 = torch.float64


def mesh(verts, faces):
    return trimesh.Trimesh(verts.detach().numpy(), faces.numpy(), process=False)


def test_faces_shape_and_range():
    faces = tube_faces(5, 8)
    assert faces.dtype == torch.int64
    assert faces.shape == (2 * 8 * 4 + 2 * 8, 3)
    assert faces.min() == 0 and faces.max() == 5 * 8 + 1


@pytest.mark.parametrize(
    "cp",
    [
        [[0.0, 0.0, 0.4], [0.05, 0.0, 0.45], [0.1, 0.05, 0.4]],
        [[0.0, 0.0, 0.5], [0.1, 0.1, 0.5], [0.2, -0.1, 0.55], [0.3, 0.0, 0.5]],
    ],
)
def test_watertight_outward(cp):
    cp = torch.tensor([cp], dtype=F64)
    radii = taper_radii(0.015, 0.008, 100, dtype=F64)[None]
    verts = bezier_tube_vertices(cp, radii)
    assert verts.shape == (1, 100 * 40 + 2, 3)
    m = mesh(verts[0], tube_faces(100, 40))
    assert m.is_watertight and m.is_winding_consistent
    assert m.volume > 0


def test_vertex_order_ring_major_caps_last():
    cp = torch.tensor([[[0.0, 0.0, 0.0], [0.0, 0.0, 0.5], [0.0, 0.0, 1.0]]], dtype=F64)
    radii = torch.full((1, 3), 0.1, dtype=F64)
    verts = bezier_tube_vertices(cp, radii, n_angles=4)
    torch.testing.assert_close(verts[0, -2], cp[0, 0])
    torch.testing.assert_close(verts[0, -1], cp[0, -1])
    torch.testing.assert_close(verts[0, 4:8, 2], torch.full((4,), 0.5, dtype=F64))  # ring 1 sits at s = 0.5
    # Tangent +z: fallback normal is +x, binormal = z x x = +y, so phi = 0 gives -N = -x, phi = pi/2 gives +y.
    torch.testing.assert_close(verts[0, 0], torch.tensor([-0.1, 0.0, 0.0], dtype=F64))
    torch.testing.assert_close(verts[0, 1], torch.tensor([0.0, 0.1, 0.0], dtype=F64), atol=1e-12, rtol=0)


def test_volume_of_straight_frustum_within_one_percent():
    L, r0, r1 = 0.2, 0.02, 0.01
    cp = torch.tensor([[[0.01, -0.02, 0.3], [0.01, -0.02 + L / 2, 0.3], [0.01, -0.02 + L, 0.3]]], dtype=F64)
    m = mesh(bezier_tube_vertices(cp, taper_radii(r0, r1, 100, dtype=F64)[None])[0], tube_faces(100, 40))
    analytic = math.pi * L / 3 * (r0**2 + r0 * r1 + r1**2)
    assert m.volume == pytest.approx(analytic, rel=0.01)
    cyl = mesh(bezier_tube_vertices(cp, torch.full((1, 100), r0, dtype=F64))[0], tube_faces(100, 40))
    assert cyl.volume == pytest.approx(math.pi * r0**2 * L, rel=0.01)


def test_radius_from_centreline():
    cp = torch.tensor([[[0.0, 0.0, 0.4], [0.05, 0.0, 0.45], [0.1, 0.05, 0.4]]], dtype=F64)
    s = ring_parameters(30, dtype=F64)
    points, frames = bezier_frames(cp, s)
    radii = torch.linspace(0.02, 0.01, 30, dtype=F64)[None]
    verts = tube_vertices(points, frames, radii, 12)
    rings = verts[:, :-2].reshape(1, 30, 12, 3)
    offsets = rings - points[:, :, None]
    torch.testing.assert_close(offsets.norm(dim=-1), radii[:, :, None].expand(1, 30, 12))
    assert (offsets * frames.tangent[:, :, None]).sum(-1).abs().max() < 1e-12


def test_batch_consistent_and_gradcheck():
    g = torch.Generator().manual_seed(0)
    cp = torch.randn(3, 3, 3, generator=g, dtype=F64) * 0.1 + torch.tensor([0, 0, 0.5], dtype=F64)
    radii = torch.rand(3, 6, generator=g, dtype=F64) * 0.01 + 0.01
    full = bezier_tube_vertices(cp, radii, n_angles=5)
    torch.testing.assert_close(full[1:2], bezier_tube_vertices(cp[1:2], radii[1:2], n_angles=5))
    cp.requires_grad_()
    radii.requires_grad_()
    assert torch.autograd.gradcheck(lambda c, r: bezier_tube_vertices(c, r, n_angles=5), (cp[:1], radii[:1]))


def test_taper_and_errors():
    torch.testing.assert_close(taper_radii(0.02, 0.01, 3), torch.tensor([0.02, 0.015, 0.01]))
    with pytest.raises(ConfigError, match="base radius must be > 0 m, got 0"):
        taper_radii(0.0, 0.01, 10)
    with pytest.raises(ConfigError, match="n_angles"):
        tube_faces(10, 2)
    with pytest.raises(ShapeError, match="radii"):
        bezier_tube_vertices(torch.zeros(2, 3, 3), torch.ones(1, 10))
    assert np.isfinite(taper_radii(0.02, 0.01, 100).numpy()).all()
