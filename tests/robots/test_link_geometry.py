"""Link geometry of the URDF manipulator model: collision primitives, one box / cylinder per link, CAD meshes."""

import logging
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

from pipeline.errors import AssetError, ConfigError
from pipeline.robots import load_urdf_robot
from pipeline.robots.mesh_io import resolve_mesh_path

ROBOTS = Path(__file__).resolve().parents[2] / "models" / "robots"
TOY_ARM = ROBOTS / "toy_arm" / "toy_arm.urdf"
TOY_ARM_MESH = ROBOTS / "toy_arm_mesh" / "toy_arm_mesh.urdf"
MESHES = ROBOTS / "toy_arm_mesh" / "meshes"


def _link_verts(model, link):
    return model.verts_link[model.vert_link_index == model.link_names.index(link)].numpy()


def _link_trimesh(model, link):
    i = model.link_names.index(link)
    mine = (model.vert_link_index == i).numpy()
    first = int(np.flatnonzero(mine)[0])
    faces = model.faces.numpy()
    faces = faces[mine[faces].all(axis=1)] - first
    return trimesh.Trimesh(_link_verts(model, link), faces, process=False)


def _bounds(verts):
    return np.stack([verts.min(axis=0), verts.max(axis=0)])


def _box_bounds(centre, extent):
    return np.stack([np.asarray(centre) - np.asarray(extent) / 2, np.asarray(centre) + np.asarray(extent) / 2])


@pytest.mark.parametrize("primitive", ["collision", "box", "cylinder"])
def test_every_link_mesh_is_closed_and_outward(primitive):
    model = load_urdf_robot(TOY_ARM_MESH, "base_link", primitive=primitive)
    for link in model.link_names:
        tm = _link_trimesh(model, link)
        assert tm.is_winding_consistent and tm.volume > 0, link
        if primitive != "collision" or link != "link3":  # link3's sphere and cylinder overlap: two closed shells
            assert tm.is_watertight, link


def test_collision_primitives_as_urdf_says():
    model = load_urdf_robot(TOY_ARM, "base_link", primitive="collision")
    base = _bounds(_link_verts(model, "base_link"))
    np.testing.assert_allclose(base, _box_bounds((0.02, 0, 0.05), (0.22, 0.16, 0.1)))
    link4 = _link_verts(model, "link4")  # cylinder r=0.03 l=0.10 turned onto x, centred at x=0.015
    np.testing.assert_allclose(link4[:, 0].min(), 0.015 - 0.05, atol=1e-6)  # pitch 1.5708 is not quite pi / 2
    np.testing.assert_allclose(link4[:, 0].max(), 0.015 + 0.05, atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(link4[:, 1:] - [0, 0.04], axis=1).max(), 0.03, atol=1e-6)
    link3 = _link_trimesh(model, "link3")  # sphere r=0.045 at 0 and cylinder r=0.035 l=0.26 from z=0
    assert link3.body_count == 2
    np.testing.assert_allclose(link3.bounds, [[-0.045, -0.045, -0.045], [0.045, 0.045, 0.26]], atol=1e-12)


def test_collision_mesh_becomes_its_convex_hull(caplog):
    with caplog.at_level(logging.INFO, logger="pipeline.robots"):
        model = load_urdf_robot(TOY_ARM_MESH, "base_link", primitive="collision", mesh_cache=None)
    assert "collision mesh package://toy_arm_mesh/meshes/link2.stl replaced by its convex hull" in caplog.text
    assert "link 'link6' has no collision geometry: using its visual geometry" in caplog.text
    capsule = trimesh.load(MESHES / "link2.stl")  # convex: its hull is itself, decimated to 300 faces
    link2 = _link_trimesh(model, "link2")
    assert link2.is_watertight and link2.is_convex and len(link2.faces) <= 300
    np.testing.assert_allclose(link2.bounds, capsule.bounds, atol=2e-3)
    assert link2.volume == pytest.approx(capsule.volume, rel=0.03)  # a box would be 1.3x the capsule's volume
    hand = _link_verts(model, "hand")  # millimetre mesh with scale 0.001, origin z=0.02
    np.testing.assert_allclose(_bounds(hand), _box_bounds((0, 0, 0.02), (0.06, 0.15, 0.04)), atol=1e-7)
    np.testing.assert_allclose(_bounds(_link_verts(model, "link6")), _box_bounds((0, 0, 0.015), (0.064, 0.064, 0.03)))


def test_box_per_link_from_primitives_and_meshes():
    model = load_urdf_robot(TOY_ARM_MESH, "base_link", primitive="box")
    for link in model.link_names:
        assert len(_link_verts(model, link)) == 98  # one subdivided box each
    # a capsule mesh: its bounding box in the element frame
    np.testing.assert_allclose(
        _bounds(_link_verts(model, "link2")), _box_bounds((0, 0, 0.15), (0.09, 0.09, 0.39)), atol=1e-7
    )
    # two elements (sphere at 0 r=0.045, cylinder to z=0.26 r=0.035): one box around both, in the link frame
    np.testing.assert_allclose(
        _bounds(_link_verts(model, "link3")), [[-0.045, -0.045, -0.045], [0.045, 0.045, 0.26]], atol=1e-12
    )
    # a rotated cylinder element: the box follows the element's frame
    link5 = _link_verts(model, "link5")  # cylinder r=0.028 l=0.07 along y (roll 90 deg), at z=0.03
    np.testing.assert_allclose(_bounds(link5), _box_bounds((0, 0, 0.03), (0.056, 0.07, 0.056)), atol=1e-6)


def test_cylinder_per_link_along_longest_side():
    model = load_urdf_robot(TOY_ARM_MESH, "base_link", primitive="cylinder")
    link2 = _link_verts(model, "link2")  # capsule r=0.045 from z=-0.045 to 0.345: cylinder along z
    np.testing.assert_allclose(_bounds(link2)[:, 2], [-0.045, 0.345], atol=1e-7)
    np.testing.assert_allclose(np.linalg.norm(link2[:, :2], axis=1).max(), 0.045, atol=1e-7)
    base = _link_verts(model, "base_link")  # 0.22 x 0.16 x 0.10 box: cylinder along x, radius 0.08
    np.testing.assert_allclose(_bounds(base)[:, 0], [0.02 - 0.11, 0.02 + 0.11], atol=1e-7)
    np.testing.assert_allclose(np.linalg.norm(base[:, 1:] - [0, 0.05], axis=1).max(), 0.08, atol=1e-7)
    hand = _link_verts(model, "hand")  # 0.06 x 0.15 x 0.04: along y, radius 0.03
    np.testing.assert_allclose(_bounds(hand)[:, 1], [-0.075, 0.075], atol=1e-7)
    np.testing.assert_allclose(np.linalg.norm(hand[:, [0, 2]] - [0, 0.02], axis=1).max(), 0.03, atol=1e-7)


def test_cylinder_mode_keeps_urdf_cylinders():
    cylinders = load_urdf_robot(TOY_ARM, "base_link", primitive="cylinder")
    collision = load_urdf_robot(TOY_ARM, "base_link", primitive="collision")
    for link in ("link1", "link2", "link4", "link5", "link6"):
        np.testing.assert_allclose(_link_verts(cylinders, link), _link_verts(collision, link), atol=1e-12)


def test_cad_loads_visual_meshes():
    model = load_urdf_robot(TOY_ARM_MESH, "base_link", primitive="cad", cad_faces_per_cm2=None)
    link2 = trimesh.load(MESHES / "link2.stl")  # package:// name, origin at the joint
    np.testing.assert_allclose(_link_verts(model, "link2"), link2.vertices)
    link1 = trimesh.load(MESHES / "link1.stl")  # relative name, origin z=0.06
    np.testing.assert_allclose(_link_verts(model, "link1"), link1.vertices + [0, 0, 0.06])
    hand = trimesh.load(MESHES / "hand_mm.stl")  # millimetres, scale 0.001, origin z=0.02
    np.testing.assert_allclose(_link_verts(model, "hand"), hand.vertices * 0.001 + [0, 0, 0.02])
    primitive = load_urdf_robot(TOY_ARM, "base_link", primitive="collision")  # visual primitives used as they are
    np.testing.assert_allclose(_link_verts(model, "link4"), _link_verts(primitive, "link4"))


def _only(link):
    """Load arguments rendering one link of the toy arm."""
    links = ("base_link", "link1", "link2", "link3", "link4", "link5", "link6", "hand", "left_finger", "right_finger")
    return {"root": "base_link", "exclude": tuple(other for other in links if other != link), "primitive": "cad"}


def test_cad_package_map_and_missing_files(tmp_path):
    urdf = tmp_path / "robot.urdf"
    shutil.copy(TOY_ARM_MESH, urdf)  # no meshes next to it
    with pytest.raises(AssetError, match="mesh 'meshes/link1.stl': file .*meshes/link1.stl not found"):
        load_urdf_robot(urdf, **_only("link1"))
    with pytest.raises(AssetError, match="package 'toy_arm_mesh' is not in package_map and no folder named"):
        load_urdf_robot(urdf, **_only("link2"))  # no folder named toy_arm_mesh above tmp_path
    model = load_urdf_robot(urdf, **_only("link2"), package_map={"toy_arm_mesh": MESHES.parent})
    assert model.link_names == ("link2",)
    np.testing.assert_allclose(_link_verts(model, "link2"), trimesh.load(MESHES / "link2.stl").vertices)
    empty = tmp_path / "empty_package"
    (empty / "meshes").mkdir(parents=True)
    with pytest.raises(AssetError, match="mesh 'package://toy_arm_mesh/meshes/link2.stl': file .*link2.stl not found"):
        load_urdf_robot(urdf, **_only("link2"), package_map={"toy_arm_mesh": empty})
    # the box and cylinder modes size links by their meshes too, so they need the files as well
    with pytest.raises(AssetError, match="mesh 'meshes/hand_mm.stl'"):
        load_urdf_robot(urdf, **(_only("hand") | {"primitive": "box"}))


def test_unreadable_mesh(tmp_path):
    (tmp_path / "meshes").mkdir()
    (tmp_path / "meshes" / "link1.stl").write_text("not a mesh")
    shutil.copy(TOY_ARM_MESH, tmp_path / "robot.urdf")
    with pytest.raises(AssetError, match="mesh 'meshes/link1.stl': cannot read .*link1.stl"):
        load_urdf_robot(tmp_path / "robot.urdf", **_only("link1"))


def test_resolve_mesh_path_by_folder_name():
    resolved = resolve_mesh_path("package://toy_arm_mesh/meshes/base.stl", TOY_ARM_MESH.parent)
    assert resolved == (MESHES / "base.stl").resolve()
    assert resolve_mesh_path(f"file://{MESHES / 'base.stl'}", "/nowhere") == MESHES / "base.stl"


@pytest.mark.parametrize("primitive", ["box", "cylinder"])
def test_volume_sized_primitives_have_the_links_volume(primitive):
    bounding = load_urdf_robot(TOY_ARM_MESH, "base_link", primitive=primitive)
    sized = load_urdf_robot(TOY_ARM_MESH, "base_link", primitive=primitive, primitive_size="volume")
    capsule = trimesh.load(MESHES / "link2.stl")  # link2's collision mesh
    sphere_and_cylinder = 4 / 3 * np.pi * 0.045**3 + np.pi * 0.035**2 * 0.26  # link3's two elements, analytic
    for link, volume, rtol in (("link2", capsule.volume, 1e-9), ("link3", sphere_and_cylinder, 0.02)):
        assert _link_trimesh(sized, link).volume == pytest.approx(volume, rel=rtol), link
    for link in sized.link_names:  # the same primitive, scaled about its centre
        a, b = _bounds(_link_verts(bounding, link)), _bounds(_link_verts(sized, link))
        np.testing.assert_allclose(a.mean(axis=0), b.mean(axis=0), atol=1e-12)
        scale = (b[1] - b[0]) / (a[1] - a[0])
        np.testing.assert_allclose(scale, scale[0], rtol=1e-9)
        assert 0.5 < scale[0] <= 1.0 + 1e-9, link  # a bounding primitive only shrinks to the link's volume
        assert _link_trimesh(sized, link).is_watertight
    boxes = [load_urdf_robot(TOY_ARM, "base_link", primitive="box", primitive_size=s) for s in ("bbox", "volume")]
    np.testing.assert_allclose(*(_link_verts(m, "base_link") for m in boxes), atol=1e-12)  # a box link stays


def test_volume_sizing_keeps_links_with_open_meshes_and_rejects_unknown_sizes(tmp_path, caplog):
    box = trimesh.creation.box((0.1, 0.2, 0.3))
    trimesh.Trimesh(box.vertices, box.faces[:-1]).export(tmp_path / "open.stl")  # one triangle missing
    (tmp_path / "robot.urdf").write_text(
        '<robot name="r"><link name="base"><collision><geometry><mesh filename="open.stl"/></geometry></collision>'
        "</link></robot>"
    )
    with caplog.at_level(logging.WARNING, logger="pipeline.robots"):
        sized = load_urdf_robot(tmp_path / "robot.urdf", "base", primitive="box", primitive_size="volume")
    assert "open.stl is not a closed mesh" in caplog.text
    np.testing.assert_allclose(_bounds(_link_verts(sized, "base")), _box_bounds((0, 0, 0), (0.1, 0.2, 0.3)), atol=1e-9)
    with pytest.raises(ConfigError, match="primitive_size.*bbox.*volume"):
        load_urdf_robot(TOY_ARM, "base_link", primitive="box", primitive_size="area")


def test_mjcf_visual_and_collision_geoms_are_told_apart(tmp_path):
    """MJCF: a geom with contype = conaffinity = 0 is visual, the others collide; capsules and ellipsoids mesh as
    closed surfaces of the right extent."""
    import trimesh

    path = tmp_path / "arm.xml"
    path.write_text(
        """<mujoco><worldbody><body name="base"><geom type="box" size="0.1 0.1 0.05"/>
        <body name="lower" pos="0 0 0.3"><joint name="j" type="hinge" axis="0 1 0"/>
          <geom type="cylinder" size="0.02 0.1" pos="0 0 0.1" contype="0" conaffinity="0" group="1"/>
          <geom type="ellipsoid" size="0.03 0.02 0.05" pos="0 0 0.25"/>
          <geom type="capsule" size="0.01 0.04" pos="0.2 0 0" contype="0" conaffinity="0"/>
        </body></body></worldbody></mujoco>"""
    )

    def lower_mesh(primitive):
        model = load_urdf_robot(path, "base", primitive=primitive, cad_faces_per_cm2=None)  # primitives undecimated
        mine = (model.vert_link_index == model.link_names.index("lower")).numpy()
        first = int(np.flatnonzero(mine)[0])
        faces = model.faces.numpy()
        faces = faces[(faces >= first).all(axis=1) & (faces < first + mine.sum()).all(axis=1)] - first
        return trimesh.Trimesh(model.verts_link.numpy()[mine], faces, process=True)

    collision = lower_mesh("collision")  # the ellipsoid only
    assert collision.is_watertight
    np.testing.assert_allclose(collision.bounds, [[-0.03, -0.02, 0.20], [0.03, 0.02, 0.30]], atol=1e-9)
    visual = lower_mesh("cad")  # the cylinder and the capsule (two closed parts)
    assert visual.is_watertight
    np.testing.assert_allclose(visual.bounds, [[-0.02, -0.02, -0.05], [0.21, 0.02, 0.2]], atol=1e-9)  # capsule: 2 * (0.04 + 0.01) long


def test_cad_meshes_are_simplified_to_the_face_budget_and_cached_on_disk(tmp_path, monkeypatch):
    """Quadric decimation (fast-simplification through trimesh) keeps each link under its face budget and close
    to the original surface; the result is cached on disk and read back without simplifying again."""
    import trimesh

    from pipeline.robots.mesh_io import simplify_mesh

    sphere = trimesh.creation.icosphere(subdivisions=5, radius=0.1)  # 20 480 faces
    verts, faces = np.asarray(sphere.vertices), np.asarray(sphere.faces, dtype=np.int64)
    cache = tmp_path / "cache"
    simple_v, simple_f = simplify_mesh(verts, faces, 500, cache)
    assert len(simple_f) <= 500 and len(list(cache.glob("*.npz"))) == 1
    radii = np.linalg.norm(simple_v, axis=1)
    assert np.abs(radii - 0.1).max() < 0.005  # vertices stay near the sphere (5 % of its radius)
    assert trimesh.Trimesh(simple_v, simple_f).is_watertight
    monkeypatch.setattr(trimesh.Trimesh, "simplify_quadric_decimation", lambda *a, **k: 1 / 0)
    again_v, again_f = simplify_mesh(verts, faces, 500, cache)  # from the cache: no decimation runs
    np.testing.assert_array_equal(again_v, simple_v)
    np.testing.assert_array_equal(again_f, simple_f)
    same_v, same_f = simplify_mesh(simple_v, simple_f, 500, None)  # under budget: unchanged
    assert same_v is simple_v and same_f is simple_f
    monkeypatch.undo()

    full = load_urdf_robot(TOY_ARM_MESH, "base_link", primitive="cad", mesh_cache=None, cad_faces=100_000,
                           cad_faces_per_cm2=None)
    small = load_urdf_robot(TOY_ARM_MESH, "base_link", primitive="cad", mesh_cache=cache, cad_faces=200,
                            cad_faces_per_cm2=None)
    counts = torch.bincount(small.vert_link_index[small.faces[:, 0]], minlength=len(small.link_names))
    assert int(counts.max()) <= 200 and len(small.faces) < len(full.faces)
    with pytest.raises(ConfigError, match="cad_faces: expected an integer >= 4, got 2"):
        load_urdf_robot(TOY_ARM_MESH, "base_link", primitive="cad", cad_faces=2)


def test_cad_face_budget_follows_the_link_surface_area():
    from pipeline.robots.link_geometry import CAD_MIN_FACES, cad_face_budget

    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.1)
    verts, faces = np.asarray(sphere.vertices), np.asarray(sphere.faces)
    area_cm2 = sphere.area * 1e4  # trimesh's area, about 1256 cm^2
    assert cad_face_budget(verts, faces, 3000, 1.0) == math.ceil(area_cm2)
    assert cad_face_budget(verts, faces, 3000, 0.5) == math.ceil(0.5 * area_cm2)
    assert cad_face_budget(verts, faces, 1000, 1.0) == 1000  # capped by cad_faces
    assert cad_face_budget(verts * 0.01, faces, 3000, 1.0) == CAD_MIN_FACES  # a tiny link keeps the floor
    assert cad_face_budget(verts, faces, 3000, None) == 3000  # off: cad_faces for every link

    # loaded: each link decimated to its own area's budget (links already under it are left as they are)
    full = load_urdf_robot(TOY_ARM_MESH, "base_link", primitive="cad", mesh_cache=None, cad_faces_per_cm2=None)
    dense = load_urdf_robot(TOY_ARM_MESH, "base_link", primitive="cad", mesh_cache=None, cad_faces_per_cm2=0.5)
    decimated = 0
    for i, name in enumerate(full.link_names):
        link_faces = full.faces[(full.vert_link_index[full.faces] == i).all(dim=1)].numpy()
        area_cm2 = trimesh.Trimesh(full.verts_link.numpy(), link_faces, process=False).area * 1e4
        budget = min(3000, max(CAD_MIN_FACES, math.ceil(0.5 * area_cm2)))
        count = int((dense.vert_link_index[dense.faces] == i).all(dim=1).sum())
        if len(link_faces) <= budget:
            assert count == len(link_faces), name
        else:
            assert count <= budget, (name, count, budget)
            decimated += 1
    assert decimated >= 3  # the toy arm's small links (wrist, hand, fingers) are the dense ones
    with pytest.raises(ConfigError, match="cad_faces_per_cm2: expected a number > 0 or None, got 0"):
        load_urdf_robot(TOY_ARM_MESH, "base_link", primitive="cad", cad_faces_per_cm2=0)


def test_decimation_keeps_a_link_of_several_parts_in_its_place():
    """A link made of parts (a box and a cylinder through it, like a motor on a bracket) keeps its extent and volume
    when decimated: fast-simplification's default aggressiveness collapsed the box into the cylinder here (a
    tenth of its length gone, a quarter of the volume left; on UR5's meshes it moved surfaces by up to 14 mm)."""
    import trimesh

    from pipeline.robots.mesh_io import simplify_mesh

    box = trimesh.creation.box((0.1, 0.1, 0.3)).subdivide().subdivide().subdivide()
    link = trimesh.util.concatenate([box, trimesh.creation.cylinder(radius=0.06, height=0.1, sections=200)])
    verts, faces = simplify_mesh(np.asarray(link.vertices), np.asarray(link.faces, dtype=np.int64), 800, None)
    simple = trimesh.Trimesh(verts, faces, process=False)
    assert len(faces) < len(link.faces) / 1.5
    np.testing.assert_allclose(simple.bounds, link.bounds, atol=1e-3)
    assert abs(simple.volume / link.volume - 1.0) < 0.02


def test_silhouette_deviation_measures_how_far_an_outline_moved():
    """Against geometry: a box grown by 2 mm along x strays 2 mm (seen across x), one moved 3 mm along z strays
    3 mm; the same mesh strays nothing; the measure is symmetric and a whole number of its pixels at most."""
    from pipeline.robots.mesh_io import silhouette_deviation

    box = trimesh.creation.box((0.1, 0.06, 0.04))
    mesh = (np.asarray(box.vertices), np.asarray(box.faces, dtype=np.int64))
    wider = (mesh[0] * [1.04, 1.0, 1.0], mesh[1])  # 2 mm further out on either side along x
    moved = (mesh[0] + [0.0, 0.0, 0.003], mesh[1])
    pixel = 0.25e-3
    assert silhouette_deviation(mesh, mesh, pixel) == 0.0
    assert silhouette_deviation(mesh, wider, pixel) == pytest.approx(0.002, abs=1.5 * pixel)
    assert silhouette_deviation(wider, mesh, pixel) == pytest.approx(silhouette_deviation(mesh, wider, pixel))
    assert silhouette_deviation(mesh, moved, pixel) == pytest.approx(0.003, abs=1.5 * pixel)
    with pytest.raises(ValueError, match="pixel_m"):
        silhouette_deviation(mesh, mesh, 0.0)


def test_decimation_within_a_silhouette_tolerance(tmp_path, monkeypatch):
    """``simplify_within`` doubles the face budget until the outline stays within the tolerance: checked against
    geometry (a decimated sphere's outline lies inside it, by the faces' largest depth below the sphere); the
    budget alone is coarser than that; the choice is cached on disk."""
    from pipeline.robots.mesh_io import simplify_mesh, simplify_within

    radius = 0.05
    sphere = trimesh.creation.icosphere(subdivisions=5, radius=radius)  # 20 480 faces
    verts, faces = np.asarray(sphere.vertices), np.asarray(sphere.faces, dtype=np.int64)

    def depth_below_sphere(mesh):  # deepest point of a face inscribed in the sphere: its plane's distance
        tri = mesh[0][mesh[1]]
        normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        plane = np.abs((normals * tri[:, 0]).sum(1)) / np.linalg.norm(normals, axis=1)
        return radius - plane.min()

    tolerance = 0.5e-3
    coarse = simplify_mesh(verts, faces, 100, None)
    assert depth_below_sphere(coarse) > 2 * tolerance  # the budget alone misses the tolerance
    cache = tmp_path / "cache"
    fine = simplify_within(verts, faces, 100, tolerance, cache)
    assert 200 <= len(fine[1]) < len(faces)
    assert depth_below_sphere(fine) < 1.5 * tolerance  # within it, give or take the measure's half-pixels
    half = simplify_mesh(verts, faces, len(fine[1]) // 2, None)  # the budget before the last doubling: too coarse
    assert depth_below_sphere(half) > tolerance
    monkeypatch.setattr(trimesh.Trimesh, "simplify_quadric_decimation", lambda *a, **k: 1 / 0)
    again = simplify_within(verts, faces, 100, tolerance, cache)  # the choice read back: no decimation
    np.testing.assert_array_equal(again[1], fine[1])
    monkeypatch.undo()

    loose = load_urdf_robot(TOY_ARM_MESH, "base_link", primitive="cad", mesh_cache=None, cad_faces=100,
                            cad_faces_per_cm2=None, cad_tolerance_m=None)
    tight = load_urdf_robot(TOY_ARM_MESH, "base_link", primitive="cad", mesh_cache=None, cad_faces=100,
                            cad_faces_per_cm2=None, cad_tolerance_m=3e-3)
    assert len(tight.faces) > len(loose.faces)
    with pytest.raises(ConfigError, match="cad_tolerance_m: expected a length > 0"):
        load_urdf_robot(TOY_ARM_MESH, "base_link", primitive="cad", cad_tolerance_m=-1.0)


def test_cad_geometry_keeps_its_meshes_within_a_millimetre_as_its_outline():
    """``"cad"`` links decimated to a budget that leaves them off their outline (the toy arm's at 100 faces a link)
    keep the same meshes within ``CAD_OUTLINE_TOLERANCE_M`` as their ``outline``, which the pose fit ends polished
    with; none where every link is within it already (the toy arm's small meshes at the default budget, or
    ``cad_tolerance_m`` at most that) or with ``outline=False``."""
    from pipeline.robots.manipulator import CAD_OUTLINE_TOLERANCE_M

    coarse = dict(primitive="cad", mesh_cache=None, cad_faces=100, cad_faces_per_cm2=None)
    model = load_urdf_robot(TOY_ARM_MESH, "base_link", **coarse)
    within = load_urdf_robot(TOY_ARM_MESH, "base_link", **coarse, cad_tolerance_m=CAD_OUTLINE_TOLERANCE_M)
    assert model.outline is not None and model.outline.outline is None and within.outline is None
    for name in ("verts_link", "faces", "vert_link_index"):
        torch.testing.assert_close(getattr(model.outline, name), getattr(within, name))
    assert len(model.outline.faces) > len(model.faces)
    assert load_urdf_robot(TOY_ARM_MESH, "base_link", **coarse, outline=False).outline is None
    assert load_urdf_robot(TOY_ARM_MESH, "base_link", primitive="cad", mesh_cache=None).outline is None


def test_hull_primitive_is_closed_convex_and_covers_the_link():
    import trimesh
    from scipy.spatial import ConvexHull

    model = load_urdf_robot(TOY_ARM_MESH, "base_link", primitive="hull", mesh_cache=None)
    cad = load_urdf_robot(TOY_ARM_MESH, "base_link", primitive="cad", mesh_cache=None, cad_faces=100_000,
                          cad_faces_per_cm2=None)
    assert model.link_names == cad.link_names
    for i, name in enumerate(model.link_names):
        mine = model.vert_link_index == i
        first = int(torch.nonzero(mine)[0])
        faces = model.faces[(model.vert_link_index[model.faces] == i).all(dim=1)] - first
        hull = trimesh.Trimesh(model.verts_link[mine].numpy(), faces.numpy(), process=True)
        assert hull.is_watertight and hull.is_convex and len(faces) <= 300, name
        inside = cad.verts_link[cad.vert_link_index == i].numpy()
        # decimation may cut a corner by a little: every CAD vertex lies inside or within 2 mm of the hull
        planes = ConvexHull(hull.vertices).equations  # (P, 4): n . x + d <= 0 inside
        outside = (inside @ planes[:, :3].T + planes[:, 3]).max()
        assert outside < 3e-3, (name, float(outside))


def test_a_hull_of_slivers_still_meets_its_face_budget(tmp_path):
    """A finely sectioned cylinder's hull is all long slivers, which the quadric decimation cannot collapse (it
    keeps all 7996 faces; Unitree Z1's links kept up to 1958 faces of 300, and its warm tracked frames took twice
    as long): the hull of its vertices thinned on a grid is decimated instead, within the budget and the shape."""
    from scipy.spatial import ConvexHull

    cylinder = trimesh.creation.cylinder(radius=0.05, height=0.2, sections=2000)
    assert len(cylinder.simplify_quadric_decimation(face_count=300, aggression=3).faces) > 300  # the gap
    cylinder.export(tmp_path / "cylinder.stl")
    (tmp_path / "robot.urdf").write_text(
        '<robot name="r"><link name="base"><visual><geometry><mesh filename="cylinder.stl"/></geometry></visual>'
        "</link></robot>")
    for budget in (300, 100):
        model = load_urdf_robot(tmp_path / "robot.urdf", "base", primitive="hull", hull_faces=budget, mesh_cache=None)
        hull = trimesh.Trimesh(model.verts_link.numpy(), model.faces.numpy(), process=True)
        assert hull.is_watertight and hull.is_convex and len(hull.faces) <= budget, budget
        np.testing.assert_allclose(hull.bounds, cylinder.bounds, atol=2e-3)
        assert hull.volume == pytest.approx(cylinder.volume, rel=0.02), budget
        planes = ConvexHull(hull.vertices).equations  # every cylinder vertex inside or within 2 mm of the hull
        assert (cylinder.vertices @ planes[:, :3].T + planes[:, 3]).max() < 2e-3, budget


def test_auto_primitive_is_the_hull_where_a_link_has_visual_meshes_and_the_collision_geometry_elsewhere(caplog):
    """The default geometry per link: the toy arm with meshes mixes links with visual meshes (base, link1-3, hand)
    and links drawn from primitives (link4 on); ``auto`` takes each link's vertices from ``hull`` or ``collision``."""
    auto = load_urdf_robot(TOY_ARM_MESH, "base_link", mesh_cache=None)  # the default
    hull = load_urdf_robot(TOY_ARM_MESH, "base_link", primitive="hull", mesh_cache=None)
    collision = load_urdf_robot(TOY_ARM_MESH, "base_link", primitive="collision", mesh_cache=None)
    assert auto.primitive == "auto" and auto.link_names == hull.link_names == collision.link_names
    kinds = {}
    for link in auto.link_names:
        mine = _link_verts(auto, link)
        as_hull = _link_verts(hull, link)
        kinds[link] = "hull" if mine.shape == as_hull.shape and np.allclose(mine, as_hull) else "collision"
        if kinds[link] == "collision":
            np.testing.assert_allclose(mine, _link_verts(collision, link), err_msg=link)
    assert [k for k, v in kinds.items() if v == "hull"] == ["base_link", "link1", "link2", "link3", "hand"]
    assert not np.allclose(_link_verts(collision, "link1")[:3], _link_verts(hull, "link1")[:3])  # they differ there
    primitives = load_urdf_robot(TOY_ARM, "base_link")  # no visual mesh anywhere: the collision primitives
    collision_only = load_urdf_robot(TOY_ARM, "base_link", primitive="collision")
    torch.testing.assert_close(primitives.verts_link, collision_only.verts_link)


def test_hull_geometry_keeps_the_visual_meshes_as_its_outline():
    """``auto`` with a visual mesh somewhere (or ``hull``) keeps the links' ``cad`` meshes beside the hulls
    (``ManipulatorModel.outline``: the pose fit asks them whether a pose explains the mask); a geometry that is
    the visual meshes already (within 1 mm: the next test), or a robot without visual meshes, has none;
    ``outline`` forces either way."""
    import pickle

    cad = load_urdf_robot(TOY_ARM_MESH, "base_link", primitive="cad", mesh_cache=None)
    for primitive in ("auto", "hull"):
        model = load_urdf_robot(TOY_ARM_MESH, "base_link", primitive=primitive, mesh_cache=None)
        outline = model.outline
        assert outline is not None and outline.primitive == "cad" and outline.outline is None
        assert outline.link_names == model.link_names and outline.joint_names == model.joint_names
        for name in ("verts_link", "faces", "vert_link_index"):
            torch.testing.assert_close(getattr(outline, name), getattr(cad, name))
        assert outline.verts_link.shape != model.verts_link.shape  # hulls, not the meshes
        q = torch.zeros(1, len(model.joint_names), dtype=torch.float64)
        torch.testing.assert_close(outline.link_poses(q), model.link_poses(q))
        again = pickle.loads(pickle.dumps(model))
        torch.testing.assert_close(again.outline.verts_link, outline.verts_link)
    assert cad.outline is None
    assert load_urdf_robot(TOY_ARM_MESH, "base_link", primitive="collision", mesh_cache=None).outline is None
    assert load_urdf_robot(TOY_ARM, "base_link").outline is None  # primitives only: drawn as they are
    assert load_urdf_robot(TOY_ARM_MESH, "base_link", mesh_cache=None, outline=False).outline is None
    forced = load_urdf_robot(TOY_ARM_MESH, "base_link", primitive="box", mesh_cache=None, outline=True)
    torch.testing.assert_close(forced.outline.verts_link, cad.verts_link)
    with pytest.raises(ConfigError, match="outline: expected True, False or None"):
        load_urdf_robot(TOY_ARM_MESH, "base_link", outline="yes")
    import dataclasses

    other = load_urdf_robot(TOY_ARM_MESH, "base_link", exclude=("hand",), primitive="cad", mesh_cache=None)
    with pytest.raises(ConfigError, match="outline: expected the same links and joints"):
        dataclasses.replace(cad, outline=other)


def test_resolve_mesh_path_with_an_empty_package_name(tmp_path):
    """``package:///PKG/rest`` (Talos' full URDFs) is ``package://PKG/rest``; no package at all is an error."""
    expected = (MESHES / "base.stl").resolve()
    assert resolve_mesh_path("package:///toy_arm_mesh/meshes/base.stl", TOY_ARM_MESH.parent) == expected
    with pytest.raises(AssetError, match="names no package"):
        resolve_mesh_path("package:///", TOY_ARM_MESH.parent)


# A COLLADA file laid out as ANYmal B's feet are: a node scaled from millimetres, bound to a material whose texture
# sampler names a <surface> that does not exist.
COLLADA_BROKEN_MATERIAL = """<?xml version="1.0" encoding="utf-8"?>
<COLLADA xmlns="http://www.collada.org/2005/11/COLLADASchema" version="1.4.1">
  <asset><unit name="meter" meter="1"/><up_axis>Z_UP</up_axis></asset>
  <library_images><image id="tex"><init_from>missing.jpg</init_from></image></library_images>
  <library_effects><effect id="paint-effect"><profile_COMMON>
    <newparam sid="tex-sampler"><sampler2D><source>no-such-surface</source></sampler2D></newparam>
    <technique sid="common"><phong><diffuse><texture texture="tex" texcoord="UV"/></diffuse></phong></technique>
  </profile_COMMON></effect></library_effects>
  <library_materials><material id="paint"><instance_effect url="#paint-effect"/></material></library_materials>
  <library_geometries><geometry id="tet"><mesh>
    <source id="tet-pos"><float_array id="tet-pos-array" count="12">0 0 0 100 0 0 0 200 0 0 0 300</float_array>
      <technique_common><accessor source="#tet-pos-array" count="4" stride="3">
        <param name="X" type="float"/><param name="Y" type="float"/><param name="Z" type="float"/>
      </accessor></technique_common></source>
    <vertices id="tet-verts"><input semantic="POSITION" source="#tet-pos"/></vertices>
    <triangles material="paint" count="4"><input semantic="VERTEX" source="#tet-verts" offset="0"/>
      <p>0 2 1 0 1 3 0 3 2 1 2 3</p></triangles>
  </mesh></geometry></library_geometries>
  <library_visual_scenes><visual_scene id="Scene"><node id="part">
    <matrix>0.001 0 0 0 0 0.001 0 0 0 0 0.001 0 0 0 0 1</matrix>
    <instance_geometry url="#tet"><bind_material><technique_common>
      <instance_material symbol="paint" target="#paint"/></technique_common></bind_material></instance_geometry>
  </node></visual_scene></library_visual_scenes>
  <scene><instance_visual_scene url="#Scene"/></scene>
</COLLADA>"""


def test_collada_with_a_broken_material_reads_its_geometry(tmp_path):
    """The gap (trimesh with pycollada): the node bound to a material it cannot resolve is dropped and the file
    reads as empty. ``read_mesh`` then reads it without its materials: the four faces, in metres (the node's
    scale)."""
    pytest.importorskip("collada")
    (tmp_path / "part.dae").write_text(COLLADA_BROKEN_MATERIAL)
    assert len(trimesh.load(tmp_path / "part.dae", force="mesh").faces) == 0
    (tmp_path / "part.urdf").write_text("<robot name='p'><link name='a'><visual><geometry><mesh filename='part.dae'/>"
                                        "</geometry></visual></link></robot>")
    model = load_urdf_robot(tmp_path / "part.urdf", "a", primitive="cad", mesh_cache=None)
    assert model.faces.shape == (4, 3)
    np.testing.assert_allclose(model.verts_link.numpy().max(axis=0), [0.1, 0.2, 0.3], atol=1e-9)
