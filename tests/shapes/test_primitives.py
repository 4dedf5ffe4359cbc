import math

import numpy as np
import pytest
import trimesh

from pipeline.errors import ConfigError
from pipeline.shapes.primitives import box_mesh, cylinder_mesh, sphere_mesh


def _trimesh(mesh):
    verts, faces = mesh
    assert verts.dtype == np.float64 and faces.dtype == np.int64
    assert verts.shape[1] == 3 and faces.shape[1] == 3
    return trimesh.Trimesh(verts, faces, process=False)


def _check_closed_outward(mesh):
    tm = _trimesh(mesh)
    assert tm.is_watertight
    assert tm.is_winding_consistent
    assert tm.volume > 0  # outward normals
    assert len(np.unique(np.round(tm.vertices, 12), axis=0)) == len(tm.vertices)  # no duplicate vertices
    assert len(np.unique(tm.faces)) == len(tm.vertices)  # every vertex used
    return tm


@pytest.mark.parametrize("subdivisions", [1, 2, 4])
def test_box_volume_area_counts(subdivisions):
    size = (0.2, 0.1, 0.3)
    tm = _check_closed_outward(box_mesh(size, subdivisions))
    n = subdivisions
    assert len(tm.vertices) == 6 * n * n + 2 and len(tm.faces) == 12 * n * n
    assert tm.volume == pytest.approx(0.2 * 0.1 * 0.3)
    assert tm.area == pytest.approx(2 * (0.2 * 0.1 + 0.1 * 0.3 + 0.2 * 0.3))
    np.testing.assert_allclose(tm.bounds, [[-0.1, -0.05, -0.15], [0.1, 0.05, 0.15]])


def test_box_default_has_interior_vertices_on_each_side():
    verts, _ = box_mesh((1.0, 1.0, 1.0))
    inner_on_top = (np.isclose(verts[:, 2], 0.5)) & (np.abs(verts[:, :2]) < 0.49).all(axis=1)
    assert inner_on_top.sum() == 9  # 4 x 4 quads -> 3 x 3 interior vertices


@pytest.mark.parametrize("segments,sections,cap_rings", [(24, 4, 2), (3, 1, 1), (16, 2, 3)])
def test_cylinder_volume_area_counts(segments, sections, cap_rings):
    r, h = 0.05, 0.4
    tm = _check_closed_outward(cylinder_mesh(r, h, segments, sections=sections, cap_rings=cap_rings))
    assert len(tm.vertices) == segments * (sections + 1 + 2 * (cap_rings - 1)) + 2
    assert len(tm.faces) == 2 * segments * (sections + 2 * cap_rings - 1)
    polygon_area = 0.5 * segments * r * r * math.sin(2 * math.pi / segments)  # inscribed prism
    side = segments * 2 * r * math.sin(math.pi / segments) * h
    assert tm.volume == pytest.approx(polygon_area * h)
    assert tm.area == pytest.approx(2 * polygon_area + side)
    np.testing.assert_allclose(tm.bounds[:, 2], [-h / 2, h / 2])
    np.testing.assert_allclose(np.linalg.norm(tm.vertices[:, :2], axis=1).max(), r)


@pytest.mark.parametrize("subdivisions", [0, 1, 2])
def test_sphere_counts_radius_volume(subdivisions):
    tm = _check_closed_outward(sphere_mesh(0.1, subdivisions))
    assert len(tm.vertices) == 10 * 4**subdivisions + 2 and len(tm.faces) == 20 * 4**subdivisions
    np.testing.assert_allclose(np.linalg.norm(tm.vertices, axis=1), 0.1)
    reference = trimesh.creation.icosphere(subdivisions=subdivisions, radius=0.1)
    assert tm.volume == pytest.approx(reference.volume, rel=1e-9)


@pytest.mark.parametrize(
    "call,message",
    [
        (lambda: box_mesh((1.0, 0.0, 1.0)), "size[1]"),
        (lambda: box_mesh((1.0, 1.0)), "three positive numbers"),
        (lambda: box_mesh((1.0, 1.0, 1.0), 0), "subdivisions: expected an int >= 1"),
        (lambda: cylinder_mesh(-1.0, 1.0), "radius"),
        (lambda: cylinder_mesh(1.0, 1.0, 2), "segments: expected an int >= 3"),
        (lambda: cylinder_mesh(1.0, 1.0, sections=0), "sections"),
        (lambda: sphere_mesh(1.0, 1.5), "subdivisions: expected an int >= 0"),
    ],
)
def test_invalid_arguments(call, message):
    with pytest.raises(ConfigError) as err:
        call()
    assert message in str(err.value)
