"""Write the example robots next to this script: ``toy_arm/`` (primitive geometry, as URDF and as MJCF) and
``toy_arm_mesh/`` (STL meshes).

Run ``python models/robots/make_example_robots.py``; the outputs are committed, and the script is deterministic
(re-running it leaves ``git status`` clean).

Both robots share one kinematic tree, a 6-DOF arm of about 0.8 m reach from the shoulder:

    base_link -joint1(z)- link1 -joint2(y)- link2 -joint3(y)- link3 -joint4(z)- link4 -joint5(y)- link5
      -joint6(z)- link6 -hand_joint(fixed)- hand -+- left_finger_joint (prismatic)  - left_finger
                                                   +- right_finger_joint (prismatic) - right_finger
                                                   +- camera_mount_joint (fixed)     - camera_mount (no geometry)
                                                   +- tcp_joint (fixed)              - tcp (no geometry)

Link sizes and offsets differ (an elbow offset, a sideways wrist, unequal fingers) so that no silhouette is
symmetric. ``toy_arm`` gives every link the same box / cylinder / sphere primitives as visual and collision;
``toy_arm/toy_arm.xml`` is the same robot in MJCF (bodies for links, hinge / slide joints, each primitive as a visual
geom with ``contype="0" conaffinity="0" group="1"`` and as a collision geom in group 3).
``toy_arm_mesh`` gives some links STL visual meshes (capsules, rounded boxes, a mesh in millimetres with
``scale="0.001 0.001 0.001"``), referenced by ``package://toy_arm_mesh/meshes/...`` or by relative paths, some links
mesh collision geometry, and ``link6`` no collision geometry at all.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

HERE = Path(__file__).resolve().parent

# joint name, type, parent, child, origin xyz, origin rpy, axis, (lower, upper)
JOINTS = [
    ("joint1", "revolute", "base_link", "link1", (0.0, 0.0, 0.10), (0.0, 0.0, 0.0), (0, 0, 1), (-2.9, 2.9)),
    ("joint2", "revolute", "link1", "link2", (0.0, 0.0, 0.12), (0.0, 0.0, 0.0), (0, 1, 0), (-1.8, 1.8)),
    ("joint3", "revolute", "link2", "link3", (0.0, 0.05, 0.30), (0.0, 0.0, 0.0), (0, 1, 0), (-2.6, 2.6)),
    ("joint4", "revolute", "link3", "link4", (0.0, 0.0, 0.26), (0.0, 0.0, 0.0), (0, 0, 1), (-2.9, 2.9)),
    ("joint5", "revolute", "link4", "link5", (0.03, 0.0, 0.08), (0.0, 0.0, 0.3), (0, 1, 0), (-2.0, 2.0)),
    ("joint6", "revolute", "link5", "link6", (0.0, 0.0, 0.06), (0.0, 0.0, 0.0), (0, 0, 1), (-3.0, 3.0)),
    ("hand_joint", "fixed", "link6", "hand", (0.0, 0.0, 0.03), (0.0, 0.0, -0.7854), None, None),
    ("left_finger_joint", "prismatic", "hand", "left_finger", (0.0, 0.02, 0.04), (0, 0, 0), (0, 1, 0), (0.0, 0.04)),
    ("right_finger_joint", "prismatic", "hand", "right_finger", (0.0, -0.02, 0.04), (0, 0, 0), (0, -1, 0),
     (0.0, 0.04)),
    ("camera_mount_joint", "fixed", "hand", "camera_mount", (0.05, 0.0, 0.02), (0.0, -1.5708, 0.0), None, None),
    ("tcp_joint", "fixed", "hand", "tcp", (0.0, 0.0, 0.09), (0.0, 0.0, 0.0), None, None),
]  # fmt: skip

# link name -> primitive elements (kind, params, origin xyz, origin rpy); used as visual and collision in toy_arm
PRIMITIVES = {
    "base_link": [("box", (0.22, 0.16, 0.10), (0.02, 0.0, 0.05), (0, 0, 0))],
    "link1": [("cylinder", (0.06, 0.12), (0.0, 0.0, 0.06), (0, 0, 0))],
    "link2": [("cylinder", (0.045, 0.30), (0.0, 0.0, 0.15), (0, 0, 0))],
    "link3": [("sphere", (0.045,), (0.0, 0.0, 0.0), (0, 0, 0)),
              ("cylinder", (0.035, 0.26), (0.0, 0.0, 0.13), (0, 0, 0))],
    "link4": [("cylinder", (0.03, 0.10), (0.015, 0.0, 0.04), (0.0, 1.5708, 0.0))],
    "link5": [("cylinder", (0.028, 0.07), (0.0, 0.0, 0.03), (1.5708, 0.0, 0.0))],
    "link6": [("cylinder", (0.032, 0.03), (0.0, 0.0, 0.015), (0, 0, 0))],
    "hand": [("box", (0.06, 0.15, 0.04), (0.0, 0.0, 0.02), (0, 0, 0))],
    "left_finger": [("box", (0.02, 0.015, 0.05), (0.0, 0.0075, 0.025), (0, 0, 0))],
    "right_finger": [("box", (0.018, 0.012, 0.045), (0.0, -0.006, 0.0225), (0, 0, 0))],
    "camera_mount": [],
    "tcp": [],
}  # fmt: skip

LINKS = list(PRIMITIVES)


def mesh_robot_geometry() -> tuple[dict[str, trimesh.Trimesh], dict[str, list], dict[str, list]]:
    """The STL meshes and the (visual, collision) elements of ``toy_arm_mesh``; a mesh element is
    ``("mesh", (filename, scale), xyz, rpy)``."""
    link2 = trimesh.creation.capsule(height=0.30, radius=0.045, count=[16, 16])  # capsules are centred at 0
    link2.apply_translation([0.0, 0.0, 0.15])  # moved in the file to span its link (z in [0, 0.3] +- r)
    meshes = {
        "base.stl": _rounded_box((0.20, 0.14, 0.08), 0.01),  # 0.22 x 0.16 x 0.10 overall
        "link1.stl": trimesh.creation.cylinder(radius=0.06, height=0.12, sections=32),
        "link2.stl": link2,
        "link3.stl": trimesh.creation.capsule(height=0.26, radius=0.035, count=[16, 16]),  # placed by its origin
        "hand_mm.stl": _rounded_box((50.0, 140.0, 30.0), 5.0),  # millimetres: 60 x 150 x 40 overall
    }
    pkg = "package://toy_arm_mesh/meshes/"
    unit = (1.0, 1.0, 1.0)
    visual = dict(PRIMITIVES)
    visual["base_link"] = [("mesh", (pkg + "base.stl", unit), (0.02, 0.0, 0.05), (0, 0, 0))]
    visual["link1"] = [("mesh", ("meshes/link1.stl", unit), (0.0, 0.0, 0.06), (0, 0, 0))]
    visual["link2"] = [("mesh", (pkg + "link2.stl", unit), (0.0, 0.0, 0.0), (0, 0, 0))]
    visual["link3"] = [("mesh", (pkg + "link3.stl", unit), (0.0, 0.0, 0.13), (0, 0, 0))]
    visual["hand"] = [("mesh", ("meshes/hand_mm.stl", (0.001, 0.001, 0.001)), (0.0, 0.0, 0.02), (0, 0, 0))]
    collision = dict(PRIMITIVES)
    collision["base_link"] = visual["base_link"]
    collision["link2"] = visual["link2"]
    collision["hand"] = visual["hand"]
    collision["link6"] = []  # visual only: the loader falls back to the visual geometry
    return meshes, visual, collision


def urdf_text(name: str, visual: dict[str, list], collision: dict[str, list]) -> str:
    lines = ['<?xml version="1.0"?>', f'<robot name="{name}">']
    for link in LINKS:
        elements = [("visual", e) for e in visual[link]] + [("collision", e) for e in collision[link]]
        if not elements:
            lines.append(f'  <link name="{link}"/>')
            continue
        lines.append(f'  <link name="{link}">')
        for tag, (kind, params, xyz, rpy) in elements:
            lines.append(f"    <{tag}>")
            lines.append(f'      <origin xyz="{_fmt(xyz)}" rpy="{_fmt(rpy)}"/>')
            lines.append(f"      <geometry>{_geometry(kind, params)}</geometry>")
            lines.append(f"    </{tag}>")
        lines.append("  </link>")
    for joint, kind, parent, child, xyz, rpy, axis, limits in JOINTS:
        lines.append(f'  <joint name="{joint}" type="{kind}">')
        lines.append(f'    <parent link="{parent}"/>')
        lines.append(f'    <child link="{child}"/>')
        lines.append(f'    <origin xyz="{_fmt(xyz)}" rpy="{_fmt(rpy)}"/>')
        if axis is not None:
            lines.append(f'    <axis xyz="{_fmt(axis)}"/>')
        if limits is not None:
            lines.append(f'    <limit lower="{limits[0]}" upper="{limits[1]}" effort="50" velocity="2"/>')
        lines.append("  </joint>")
    lines.append("</robot>")
    return "\n".join(lines) + "\n"


def mjcf_text(name: str, primitives: dict[str, list]) -> str:
    """The robot as MJCF: one body per link (placed by its joint's origin), joints at the body origins."""
    below: dict[str, list] = {link: [] for link in LINKS}
    for joint in JOINTS:
        below[joint[2]].append(joint)
    lines = [f'<mujoco model="{name}">', '  <compiler angle="radian"/>', "  <worldbody>"]

    def body(link: str, joint: tuple | None, depth: int) -> None:
        pad = "  " * depth
        place = ' pos="0 0 0"' if joint is None else f' pos="{_fmt(joint[4])}" quat="{_fmt(_quat(joint[5]))}"'
        lines.append(f'{pad}<body name="{link}"{place}>')
        if joint is not None and joint[1] != "fixed":
            kind = {"revolute": "hinge", "prismatic": "slide"}[joint[1]]
            lower, upper = joint[7]
            lines.append(f'{pad}  <joint name="{joint[0]}" type="{kind}" axis="{_fmt(joint[6])}" '
                         f'limited="true" range="{lower} {upper}"/>')
        for kind, params, xyz, rpy in primitives[link]:
            size = [v / 2 for v in params] if kind == "box" else [params[0], params[-1] / 2][: 2 if kind == "cylinder" else 1]
            where = f'type="{kind}" size="{_fmt(size)}" pos="{_fmt(xyz)}" quat="{_fmt(_quat(rpy))}"'
            lines.append(f'{pad}  <geom {where} contype="0" conaffinity="0" group="1"/>')
            lines.append(f'{pad}  <geom {where} group="3"/>')
        for child in below[link]:
            body(child[3], child, depth + 1)
        lines.append(f"{pad}</body>")

    body(LINKS[0], None, 2)
    lines += ["  </worldbody>", "</mujoco>"]
    return "\n".join(lines) + "\n"


def _quat(rpy: tuple) -> tuple:
    """URDF roll-pitch-yaw to a MuJoCo quaternion ``(w, x, y, z)``."""
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_euler("xyz", rpy).as_quat()  # extrinsic x, y, z: Rz(yaw) Ry(pitch) Rx(roll)
    return (w, x, y, z)


def main() -> None:
    toy_arm = HERE / "toy_arm"
    toy_arm.mkdir(exist_ok=True)
    (toy_arm / "toy_arm.urdf").write_text(urdf_text("toy_arm", PRIMITIVES, PRIMITIVES))
    (toy_arm / "toy_arm.xml").write_text(mjcf_text("toy_arm", PRIMITIVES))

    meshes, visual, collision = mesh_robot_geometry()
    toy_arm_mesh = HERE / "toy_arm_mesh"
    (toy_arm_mesh / "meshes").mkdir(parents=True, exist_ok=True)
    for filename, mesh in meshes.items():
        mesh.export(toy_arm_mesh / "meshes" / filename)
    (toy_arm_mesh / "toy_arm_mesh.urdf").write_text(urdf_text("toy_arm_mesh", visual, collision))


def _rounded_box(inner: tuple[float, float, float], radius: float) -> trimesh.Trimesh:
    """Box of half-extents ``inner / 2`` grown by ``radius`` (the convex hull of spheres at its corners)."""
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=radius)
    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * np.asarray(inner) / 2
    points = (corners[:, None, :] + sphere.vertices[None, :, :]).reshape(-1, 3)  # (8 * S, 3)
    return trimesh.convex.convex_hull(points)


def _geometry(kind: str, params: tuple) -> str:
    if kind == "box":
        return f'<box size="{_fmt(params)}"/>'
    if kind == "cylinder":
        return f'<cylinder radius="{params[0]}" length="{params[1]}"/>'
    if kind == "sphere":
        return f'<sphere radius="{params[0]}"/>'
    filename, scale = params
    return f'<mesh filename="{filename}" scale="{_fmt(scale)}"/>'


def _fmt(values: tuple) -> str:
    return " ".join(repr(float(v)) for v in values)


if __name__ == "__main__":
    main()
