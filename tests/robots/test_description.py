"""FK of the manipulator model (the description's pytorch-kinematics chain) against an independent numpy FK
(written here from the URDF XML), MuJoCo's own kinematics for MJCF, and pytorch-kinematics' own builders (the gaps
our chain adapter works around); real robots (example-robot-data, robosuite) where installed; gradients, dtypes,
pickling."""

import importlib.util
import pickle
import sysconfig
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
import torch

from pipeline.errors import ConfigError, ShapeError
from pipeline.robots.manipulator import load_urdf_robot

ROBOTS = Path(__file__).resolve().parents[2] / "models" / "robots"
TOY_ARM = ROBOTS / "toy_arm" / "toy_arm.urdf"


def _reference_fk(urdf_text: str, values: dict[str, float]) -> dict[str, np.ndarray]:
    """T_base_link for every link of a URDF: a plain recursive numpy FK (quaternions for the joint rotation)."""
    robot = ET.fromstring(urdf_text)
    joints = {j.find("child").get("link"): j for j in robot.findall("joint")}
    mimic = {}
    for j in robot.findall("joint"):
        m = j.find("mimic")
        if m is not None:
            mimic[j.get("name")] = (m.get("joint"), float(m.get("multiplier", 1)), float(m.get("offset", 0)))

    def elementary(axis: int, angle: float) -> np.ndarray:
        c, s = np.cos(angle), np.sin(angle)
        i, k = [(1, 2), (2, 0), (0, 1)][axis]
        R = np.eye(3)
        R[i, i], R[i, k], R[k, i], R[k, k] = c, -s, s, c
        return R

    def origin(el) -> np.ndarray:
        o = el.find("origin")
        xyz = [float(v) for v in o.get("xyz").split()] if o is not None else [0, 0, 0]
        r, p, y = [float(v) for v in o.get("rpy").split()] if o is not None else [0, 0, 0]
        T = np.eye(4)
        T[:3, :3] = elementary(2, y) @ elementary(1, p) @ elementary(0, r)
        T[:3, 3] = xyz
        return T

    def value(name: str) -> float:
        if name in mimic:
            master, multiplier, offset = mimic[name]
            return multiplier * value(master) + offset
        return values[name]

    def motion(joint) -> np.ndarray:
        kind, T = joint.get("type"), np.eye(4)
        if kind == "fixed":
            return T
        axis_el = joint.find("axis")
        axis = np.array([float(v) for v in axis_el.get("xyz").split()]) if axis_el is not None else np.eye(3)[0]
        axis = axis / np.linalg.norm(axis)
        q = value(joint.get("name"))
        if kind == "prismatic":
            T[:3, 3] = q * axis
            return T
        w, (x, y, z) = np.cos(q / 2), np.sin(q / 2) * axis
        T[:3, :3] = [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
        return T

    def pose(link: str) -> np.ndarray:
        if link not in joints:
            return np.eye(4)
        joint = joints[link]
        return pose(joint.find("parent").get("link")) @ origin(joint) @ motion(joint)

    return {link.get("name"): pose(link.get("name")) for link in robot.findall("link")}


def _random_joints(model, batch: int, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    lower = model.joint_lower.clamp(min=-3.0)
    upper = model.joint_upper.clamp(max=3.0)
    return lower + (upper - lower) * torch.rand(batch, len(model.joint_names), generator=g, dtype=torch.float64)


@pytest.mark.parametrize("root", ["base_link", "link2", "hand"])
def test_every_frame_matches_reference_fk(root):
    model = load_urdf_robot(TOY_ARM, root)
    q = _random_joints(model, 3, seed=0)
    frames = model.link_frames_in_root(q)  # (B, K, 4, 4)
    assert frames.shape == (3, len(model.frame_names), 4, 4) and frames.dtype == torch.float64
    text = TOY_ARM.read_text()
    for b in range(3):
        above_root = {f"joint{i}": 0.3 for i in range(1, 7)}  # readings of joints above root must not matter
        values = above_root | dict(zip(model.joint_names, q[b].tolist()))
        reference = _reference_fk(text, values)
        T_root_base = np.linalg.inv(reference[root])
        for k, name in enumerate(model.frame_names):
            np.testing.assert_allclose(frames[b, k].numpy(), T_root_base @ reference[name], atol=1e-12, err_msg=name)
    # the fixed-joint and prismatic frames are there
    if root != "link2":
        assert {"hand", "camera_mount", "tcp", "left_finger", "right_finger"} <= set(model.frame_names)


def test_link_poses_are_rendered_frames_in_order():
    model = load_urdf_robot(TOY_ARM, "base_link")
    q = _random_joints(model, 2, seed=1)
    poses = model.link_poses(q)
    frames = model.link_frames_in_root(q)
    assert poses.shape == (2, len(model.link_names), 4, 4)
    for i, name in enumerate(model.link_names):
        torch.testing.assert_close(poses[:, i], frames[:, model.frame_index(name)])


def test_pytorch_kinematics_builder_rounds_origins_to_float32():
    """The gap the chain adapter (``description._chain``) works around: ``pk.build_chain_from_urdf`` converts joint
    origins in float32, so its FK is ~1e-8 m off even after ``.to(float64)``; ours equals the numpy FK to 1e-12 (see
    ``test_every_frame_matches_reference_fk``). If this test fails, pytorch-kinematics fixed it: build with it."""
    import pytorch_kinematics as pk

    chain = pk.build_chain_from_urdf(TOY_ARM.read_bytes()).to(dtype=torch.float64)
    model = load_urdf_robot(TOY_ARM, "base_link")
    assert list(model.joint_names) == chain.get_joint_parameter_names()
    q = _random_joints(model, 4, seed=2)
    expected = chain.forward_kinematics(q)
    ours = model.link_frames_in_root(q)
    gap = max(float((ours[:, k] - expected[name].get_matrix()).abs().max()) for k, name in enumerate(model.frame_names))
    assert 1e-10 < gap < 1e-6


def test_pytorch_kinematics_builder_fails_on_one_link_urdf(tmp_path):
    """A gap the adapter works around: ``pk.build_chain_from_urdf`` raises on a description without joints."""
    import pytorch_kinematics as pk

    text = "<robot name='one'><link name='a'><visual><geometry><box size='0.1 0.2 0.3'/></geometry></visual></link></robot>"
    with pytest.raises(Exception):
        pk.build_chain_from_urdf(text)
    path = tmp_path / "one.urdf"
    path.write_text(text)
    model = load_urdf_robot(path, "a")
    assert model.link_names == ("a",) and model.joint_names == ()
    torch.testing.assert_close(model.link_poses(torch.zeros(1, 0, dtype=torch.float64)), torch.eye(4, dtype=torch.float64)[None, None])


def _mujoco_frames(xml_path: Path, model, q: torch.Tensor) -> np.ndarray:
    """``(B, K, 4, 4)`` T_root_frame of the model's frames by MuJoCo's own ``mj_kinematics``."""
    mujoco = pytest.importorskip("mujoco")
    mj = mujoco.MjModel.from_xml_path(str(xml_path))
    data = mujoco.MjData(mj)
    out = np.zeros((q.shape[0], len(model.frame_names), 4, 4))
    for b in range(q.shape[0]):
        data.qpos[:] = mj.qpos0
        for name, value in zip(model.joint_names, q[b].tolist()):
            data.qpos[mj.joint(name).qposadr[0]] = value
        mujoco.mj_kinematics(mj, data)

        def pose(body: str) -> np.ndarray:
            i = mj.body(body).id
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = data.xmat[i].reshape(3, 3), data.xpos[i]
            return T

        T_root_world = np.linalg.inv(pose(model.root))
        for k, name in enumerate(model.frame_names):
            out[b, k] = T_root_world @ pose(name)
    return out


MJCF_OFFSET_JOINTS = """<mujoco model="offsets"><compiler angle="degree"/><worldbody>
  <body name="base"><geom type="box" size="0.1 0.1 0.05"/>
    <body name="upper" pos="0 0 0.1" euler="10 0 20">
      <joint name="shoulder" type="hinge" pos="0.05 0.02 0" axis="0 1 1" range="-90 90"/>
      <geom type="capsule" size="0.03 0.15" pos="0 0 0.15"/>
      <body name="lower" pos="0 0 0.3">
        <joint name="slide" type="slide" pos="0 0.1 0.2" axis="0 0 1" range="0 0.1"/>
        <geom type="cylinder" size="0.02 0.1" pos="0 0 0.1" contype="0" conaffinity="0"/>
        <geom type="ellipsoid" size="0.03 0.02 0.05" pos="0 0 0.25"/>
      </body>
    </body>
  </body></worldbody></mujoco>"""


def test_mjcf_joints_away_from_body_origin_match_mujoco(tmp_path):
    """MJCF joints placed away from their body's origin (``pos``) and angles in degrees: our FK equals MuJoCo's;
    pytorch-kinematics' own MJCF builder cannot be used (the gap the adapter works around): with mujoco 4 it
    raises (its joint-type map is keyed by enum members, MuJoCo 4 gives int32), and its chain leaves out the shift
    back of a joint placed away from its body's origin."""
    pk = pytest.importorskip("pytorch_kinematics")
    path = tmp_path / "offsets.xml"
    path.write_text(MJCF_OFFSET_JOINTS)
    model = load_urdf_robot(path, "base")
    assert model.joint_names == ("shoulder", "slide") and model.format == "mjcf"
    assert model.link_names == ("base", "upper", "lower")
    q = _random_joints(model, 3, seed=7)
    expected = _mujoco_frames(path, model, q)
    np.testing.assert_allclose(model.link_frames_in_root(q).numpy(), expected, atol=1e-12)
    try:
        theirs = pk.build_chain_from_mjcf(MJCF_OFFSET_JOINTS).to(dtype=torch.float64).forward_kinematics(q)
    except KeyError:
        return
    T_base = theirs["base"].get_matrix().inverse()
    gap = (T_base @ theirs["lower"].get_matrix() - model.link_frames_in_root(q)[:, 2]).abs().max()
    assert float(gap) > 1e-3


def test_toy_arm_urdf_and_mjcf_give_the_same_model():
    """The example robot written by its generator as URDF and as MJCF: same links, joints, FK and meshes."""
    urdf = load_urdf_robot(TOY_ARM, "base_link")
    mjcf = load_urdf_robot(TOY_ARM.with_suffix(".xml"), "base_link")
    assert (urdf.format, mjcf.format) == ("urdf", "mjcf")
    assert mjcf.link_names == urdf.link_names and mjcf.joint_names == urdf.joint_names
    assert mjcf.frame_names == urdf.frame_names
    torch.testing.assert_close(mjcf.joint_lower, urdf.joint_lower)
    q = _random_joints(urdf, 4, seed=8)
    np.testing.assert_allclose(mjcf.link_frames_in_root(q).numpy(), urdf.link_frames_in_root(q).numpy(), atol=1e-9)
    np.testing.assert_allclose(mjcf.link_frames_in_root(q).numpy(), _mujoco_frames(TOY_ARM.with_suffix(".xml"), mjcf, q),
                               atol=1e-12)  # fmt: skip
    torch.testing.assert_close(mjcf.faces, urdf.faces)
    np.testing.assert_allclose(mjcf.mesh_in_root(q).numpy(), urdf.mesh_in_root(q).numpy(), atol=1e-9)


ROBOT_DATA = Path(sysconfig.get_paths()["purelib"]) / "cmeel.prefix" / "share" / "example-robot-data" / "robots"
REAL_URDFS = {
    "baxter": ("baxter_description/urdf/baxter.urdf", "left_arm_mount"),
    "panda": ("panda_description/urdf/panda.urdf", "panda_link0"),
    "ur5": ("ur_description/urdf/ur5_robot.urdf", "base_link"),
    # the cross-robot benchmark's held-out arms (benchmarks/acceptance_robots.py HELD_OUT)
    "kinova": ("kinova_description/robots/kinova.urdf", "j2s6s200_link_base"),
    "xarm7": ("xarm_description/urdf/xarm7.urdf", "link_base"),
    "z1": ("z1_description/urdf/z1.urdf", "link00"),
    "so100": ("so_arm_description/urdf/so100.urdf", "base"),
}


@pytest.mark.parametrize("robot", sorted(REAL_URDFS))
def test_real_robot_urdf_fk_matches_numpy(robot, capfd):
    """Baxter, Panda, UR5 and the held-out arms (the example-robot-data package, a test extra): FK of every frame
    below the root against the numpy FK to 1e-9 m, mimic fingers included; the parser's warnings stay off stderr."""
    relative, root = REAL_URDFS[robot]
    path = ROBOT_DATA / relative
    if not path.is_file():
        pytest.skip(f"example-robot-data is not installed ({path} missing): pip install example-robot-data")
    model = load_urdf_robot(path, root)
    assert capfd.readouterr().err == ""
    q = _random_joints(model, 3, seed=9)
    frames = model.link_frames_in_root(q).numpy()
    text = path.read_text()
    for b in range(3):
        values = {name: 0.0 for name in model.description_joint_names} | dict(zip(model.joint_names, q[b].tolist()))
        reference = _reference_fk(text, values)
        T_root_base = np.linalg.inv(reference[root])
        for k, name in enumerate(model.frame_names):
            np.testing.assert_allclose(frames[b, k], T_root_base @ reference[name], atol=1e-9, err_msg=name)


def _robosuite_robots() -> Path | None:
    spec = importlib.util.find_spec("robosuite")
    if spec is None or spec.origin is None:
        return None
    return Path(spec.origin).parent / "models" / "assets" / "robots"


@pytest.mark.parametrize("robot", ["panda", "ur5e"])
def test_real_mjcf_fk_matches_mujoco(robot):
    """robosuite's Panda and UR5e MJCF (meshes in files, a test extra; never committed): FK against
    ``mj_kinematics`` to 1e-9 m, CAD meshes read from the compiled model."""
    folder = _robosuite_robots()
    if folder is None:
        pytest.skip("robosuite is not installed (pip install --no-deps robosuite: only its MJCF assets are used)")
    path = folder / robot / "robot.xml"
    model = load_urdf_robot(path, "base", primitive="cad", cad_faces_per_cm2=None, outline=False)  # 3000 faces a link
    assert len(model.joint_names) >= 6 and model.faces.shape[0] > 10_000
    q = _random_joints(model, 3, seed=10)
    np.testing.assert_allclose(model.link_frames_in_root(q).numpy(), _mujoco_frames(path, model, q), atol=1e-9)


def test_mimic_joint_follows_its_master(tmp_path):
    text = TOY_ARM.read_text().replace(
        '<child link="right_finger"/>',
        '<child link="right_finger"/>\n    <mimic joint="left_finger_joint" multiplier="0.5" offset="0.01"/>',
    )
    path = tmp_path / "mimic.urdf"
    path.write_text(text)
    model = load_urdf_robot(path, "hand")
    assert model.joint_names == ("left_finger_joint",)
    q = torch.tensor([[0.02]], dtype=torch.float64)
    frames = model.link_frames_in_root(q)
    reference = _reference_fk(text, {"left_finger_joint": 0.02, **{f"joint{i}": 0.0 for i in range(1, 7)}})
    T_hand_base = np.linalg.inv(reference["hand"])
    for k, name in enumerate(model.frame_names):
        np.testing.assert_allclose(frames[0, k].numpy(), T_hand_base @ reference[name], atol=1e-12, err_msg=name)
    right = frames[0, model.frame_index("right_finger"), 1, 3]
    assert float(right) == pytest.approx(-0.02 - (0.5 * 0.02 + 0.01))


def test_no_movable_joint_needed():
    model = load_urdf_robot(TOY_ARM, "hand", exclude=("left_finger", "right_finger"))
    assert model.joint_names == () and model.link_names == ("hand",)
    poses = model.link_poses(torch.zeros(2, 0))
    torch.testing.assert_close(poses, torch.eye(4).expand(2, 1, 4, 4))


def test_gradcheck_link_poses_wrt_joints():
    model = load_urdf_robot(TOY_ARM, "base_link")
    q = _random_joints(model, 2, seed=3).requires_grad_(True)
    assert torch.autograd.gradcheck(model.link_poses, (q,))


def test_gradcheck_mesh_in_root_wrt_joints_and_offsets():
    model = load_urdf_robot(TOY_ARM, "link4", primitive="box")
    V = model.verts_link.shape[0]
    picked = torch.tensor([0, 150, 300, V // 2, V - 100, V - 1])  # vertices on different links
    assert len(set(model.vert_link_index[picked].tolist())) >= 4
    q = _random_joints(model, 2, seed=4).requires_grad_(True)
    offsets = (0.01 * torch.randn(2, len(picked), 3, dtype=torch.float64)).requires_grad_(True)

    def picked_vertices(q, offsets_picked):
        full = torch.zeros(2, V, 3, dtype=torch.float64)
        full[:, picked] = offsets_picked
        return model.mesh_in_root(q, full)[:, picked]

    assert torch.autograd.gradcheck(picked_vertices, (q, offsets))


def test_mesh_in_root_applies_offsets_in_link_frame():
    model = load_urdf_robot(TOY_ARM, "base_link")
    q = _random_joints(model, 2, seed=5)
    offsets = 0.01 * torch.randn(2, model.verts_link.shape[0], 3, generator=torch.Generator().manual_seed(0),
                                 dtype=torch.float64)  # fmt: skip
    verts = model.mesh_in_root(q, offsets)
    poses = model.link_poses(q)
    for i in range(len(model.link_names)):
        mine = model.vert_link_index == i
        local = model.verts_link[mine] + offsets[:, mine]  # (B, n, 3)
        expected = local @ poses[:, i, :3, :3].transpose(1, 2) + poses[:, i, None, :3, 3]
        torch.testing.assert_close(verts[:, mine], expected)
    torch.testing.assert_close(model.mesh_in_root(q), model.mesh_in_root(q, torch.zeros_like(offsets)))


def test_dtype_follows_input_and_shape_errors():
    model = load_urdf_robot(TOY_ARM, "base_link")
    J, V = len(model.joint_names), model.verts_link.shape[0]
    assert model.mesh_in_root(torch.zeros(1, J)).dtype == torch.float32
    assert model.link_poses(torch.zeros(1, J, dtype=torch.float64)).dtype == torch.float64
    with pytest.raises(ShapeError, match=rf"joint_angles: expected shape \(\*, {J}\), got \(1, 3\)"):
        model.link_poses(torch.zeros(1, 3))
    with pytest.raises(ShapeError, match="floating point"):
        model.link_poses(torch.zeros(1, J, dtype=torch.int64))
    with pytest.raises(ShapeError, match=rf"vertex_offsets: expected shape \(2, {V}, 3\)"):
        model.mesh_in_root(torch.zeros(2, J), torch.zeros(1, V, 3))


@pytest.mark.parametrize("path", [TOY_ARM, TOY_ARM.with_suffix(".xml")], ids=["urdf", "mjcf"])
def test_pickle_round_trip(path):
    model = load_urdf_robot(path, "base_link", tip="left_finger")
    copy = pickle.loads(pickle.dumps(model))
    q = _random_joints(model, 2, seed=6)
    torch.testing.assert_close(copy.link_frames_in_root(q), model.link_frames_in_root(q), rtol=0, atol=0)
    torch.testing.assert_close(copy.mesh_in_root(q), model.mesh_in_root(q))
    assert copy.link_names == model.link_names and copy.joint_names == model.joint_names


SDF_TWO_LINKS = """<?xml version="1.0"?>
<sdf version="1.6"><model name="two">
  <link name="base"><pose>0.1 0 0 0 0 0.2</pose>{inertial}
    <visual name="v"><geometry><box><size>0.2 0.2 0.1</size></box></geometry></visual></link>
  <link name="arm"><pose>0 0.05 0.2 0.3 -0.4 0.5</pose>{inertial}
    <visual name="v"><pose>0 0 0.1 0 0 0</pose><geometry><cylinder><radius>0.03</radius><length>0.2</length>
    </cylinder></geometry></visual></link>
  <joint name="j1" type="revolute"><parent>base</parent><child>arm</child>
    <axis><xyz>0 1 0</xyz><limit><lower>-1</lower><upper>1</upper></limit></axis></joint>
</model></sdf>""".replace(
    "{inertial}",
    "<inertial><mass>1</mass><inertia><ixx>1</ixx><ixy>0</ixy><ixz>0</ixz><iyy>1</iyy><iyz>0</iyz><izz>1</izz>"
    "</inertia></inertial>",
)


def test_sdf_model_fk_and_geometry(tmp_path):
    """SDF (link poses in the model frame, roll-pitch-yaw about fixed axes, joint axis in the child frame): FK
    against a numpy composition, limits and visual primitives read."""
    path = tmp_path / "two.sdf"
    path.write_text(SDF_TWO_LINKS)
    model = load_urdf_robot(path, "base")
    assert (model.format, model.link_names, model.joint_names) == ("sdf", ("base", "arm"), ("j1",))
    assert model.joint_lower.tolist() == [-1.0] and model.joint_upper.tolist() == [1.0]

    def pose(x, y, z, roll, pitch, yaw):
        def rot(axis, a):
            c, s = np.cos(a), np.sin(a)
            i, k = [(1, 2), (2, 0), (0, 1)][axis]
            R = np.eye(3)
            R[i, i], R[i, k], R[k, i], R[k, k] = c, -s, s, c
            return R

        T = np.eye(4)
        T[:3, :3], T[:3, 3] = rot(2, yaw) @ rot(1, pitch) @ rot(0, roll), (x, y, z)
        return T

    q = 0.35
    expected = np.linalg.inv(pose(0.1, 0, 0, 0, 0, 0.2)) @ pose(0, 0.05, 0.2, 0.3, -0.4, 0.5) @ pose(0, 0, 0, 0, q, 0)
    frames = model.link_frames_in_root(torch.tensor([[q]], dtype=torch.float64))
    np.testing.assert_allclose(frames[0, 1].numpy(), expected, atol=1e-12)
    assert model.verts_link.shape[0] > 0


# What ROS tools accept and pytorch-kinematics' urdf_parser_py (0.10.0) refuses: a <texture/> without filename (iCub,
# Romeo) and PR2's transmissions; neither is read by the fit, so they are left out before parsing.
URDF_ROS_EXTRAS = """<robot name='extras'>
  <material name='metal'><color rgba='0.5 0.5 0.5 1'/><texture/></material>
  <link name='base'><visual><geometry><box size='0.1 0.1 0.1'/></geometry><material name='metal'/></visual></link>
  <link name='arm'><visual><origin xyz='0 0 0.1'/><geometry><cylinder radius='0.02' length='0.2'/></geometry>
    <material name='paint'><texture/></material></visual></link>
  <joint name='j1' type='revolute'><parent link='base'/><child link='arm'/><origin xyz='0 0 0.05'/>
    <axis xyz='0 1 0'/><limit lower='-1' upper='1' effort='1' velocity='1'/></joint>
  <transmission name='wrist' type='WristTransmission'>
    <rightActuator mechanicalReduction='60' name='r_motor'/><flexJoint mechanicalReduction='-1.0' name='j1'/>
  </transmission>
  <gazebo reference='arm'><material>Gazebo/Grey</material></gazebo>
</robot>"""


def test_urdf_with_textures_without_file_and_transmissions_loads(tmp_path):
    """A gap the adapter works around (``description.UNREAD_ELEMENTS``): urdf_parser_py raises on the raw text;
    ours loads it, with the same links, joint and geometry as the description without those elements."""
    from pytorch_kinematics.urdf_parser_py.urdf import URDF

    with pytest.raises(Exception):
        URDF.from_xml_string(URDF_ROS_EXTRAS)
    (tmp_path / "extras.urdf").write_text(URDF_ROS_EXTRAS)
    root = ET.fromstring(URDF_ROS_EXTRAS)
    for parent in list(root.iter()):
        for child in list(parent):
            if child.tag in ("material", "transmission", "gazebo"):
                parent.remove(child)
    (tmp_path / "plain.urdf").write_text(ET.tostring(root, encoding="unicode"))
    extras, plain = (load_urdf_robot(tmp_path / f"{name}.urdf", "base") for name in ("extras", "plain"))
    assert extras.link_names == plain.link_names == ("base", "arm") and extras.joint_names == ("j1",)
    q = torch.tensor([[0.4]], dtype=torch.float64)
    torch.testing.assert_close(extras.mesh_in_root(q), plain.mesh_in_root(q), rtol=0, atol=0)


def _sdf_with_mesh(mesh_uri: str) -> str:
    return f"""<?xml version="1.0"?>
<sdf version="1.6"><model name="meshy">
  <link name="base"><visual name="v"><geometry><mesh><uri>{mesh_uri}</uri><scale>2 3 0.5</scale></mesh></geometry>
    <material><ambient>0.3 0.3 0.3 1</ambient></material></visual></link>
  <link name="arm"><pose>0 0 0.2 0 0 0</pose>
    <visual name="v"><geometry><box><size>0.05 0.05 0.2</size></box></geometry></visual></link>
  <joint name="fixed_to_world" type="fixed"><parent>world</parent><child>base</child></joint>
  <joint name="j1" type="revolute"><parent>base</parent><child>arm</child><axis><xyz>0 1 0</xyz></axis></joint>
</model></sdf>"""


def test_sdf_mesh_by_uri_with_scale_and_a_joint_to_the_world(tmp_path):
    """Gazebo's SDF names a mesh file ``<uri>`` (``model://MODEL/...`` looked up like ``package://``) with a
    ``<scale>``; pytorch-kinematics' SDF reader expects ``<filename>`` and raises on the raw text. Ours reads it:
    the mesh's vertices are the file's, scaled per axis; a joint from ``world`` only fixes the model (skipped)."""
    import trimesh
    from pytorch_kinematics.urdf_parser_py.sdf import SDF

    box = trimesh.creation.box(extents=(0.1, 0.2, 0.3))
    (tmp_path / "meshy" / "meshes").mkdir(parents=True)
    box.export(tmp_path / "meshy" / "meshes" / "box.stl")
    text = _sdf_with_mesh("model://meshy/meshes/box.stl")
    with pytest.raises(Exception):
        SDF.from_xml_string(text)
    (tmp_path / "meshy" / "model.sdf").write_text(text)
    model = load_urdf_robot(tmp_path / "meshy" / "model.sdf", "base", primitive="cad", mesh_cache=None)
    assert model.link_names == ("base", "arm") and model.joint_names == ("j1",)
    base = model.verts_link[model.vert_link_index == 0].numpy()
    np.testing.assert_allclose(base.max(axis=0) - base.min(axis=0), [0.2, 0.6, 0.15], atol=1e-9)


def test_closed_kinematic_loop_is_refused_by_name(tmp_path):
    text = SDF_TWO_LINKS.replace("</model>", "<joint name='j2' type='revolute'><parent>base</parent><child>arm</child>"
                                             "<axis><xyz>1 0 0</xyz></axis></joint></model>")
    (tmp_path / "loop.sdf").write_text(text)
    with pytest.raises(ConfigError, match="link 'arm' is the child of two joints \\(a closed kinematic loop"):
        load_urdf_robot(tmp_path / "loop.sdf", "base")


SDF_FRAMES = """<?xml version="1.0"?>
<sdf version="1.9"><model name="framed">
  <link name="base"><pose>0.1 -0.2 0.05 0.3 0.1 -0.4</pose>
    <visual name="v"><geometry><box><size>0.2 0.2 0.1</size></box></geometry></visual></link>
  <link name="arm"><pose relative_to="base" degrees="true">0 0.05 0.3 20 -10 45</pose>
    <visual name="v"><pose>0 0 0.1 0 0 0</pose><geometry><cylinder><radius>0.03</radius><length>0.2</length>
    </cylinder></geometry></visual></link>
  <joint name="j1" type="revolute"><parent>base</parent><child>arm</child>
    <pose rotation_format="quat_xyzw">0.02 0 -0.1 0 0.3826834 0 0.9238795</pose>
    <axis><xyz expressed_in="__model__">0.6 0 0.8</xyz></axis></joint>
</model></sdf>"""


def test_sdf_poses_relative_to_frames_a_joint_pose_and_an_axis_in_the_model_frame(tmp_path):
    """SDF 1.7+ frames (pytorch-kinematics' SDF reader takes every pose as the model's and the axis as the child's):
    the arm's FK against a rotation about the joint's line written in the model frame, with numpy."""
    def pose(xyz, rpy):
        T = np.eye(4)
        (cr, cp, cy), (sr, sp, sy) = np.cos(rpy), np.sin(rpy)
        T[:3, :3] = [[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                     [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr], [-sp, cp * sr, cp * cr]]
        T[:3, 3] = xyz
        return T

    def about_line(axis, point, angle):  # Rodrigues, about the line through point
        k = np.asarray(axis) / np.linalg.norm(axis)
        K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
        T = np.eye(4)
        T[:3, :3] = np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K
        T[:3, 3] = point - T[:3, :3] @ point
        return T

    (tmp_path / "framed.sdf").write_text(SDF_FRAMES)
    model = load_urdf_robot(tmp_path / "framed.sdf", "base")
    T_model_base = pose((0.1, -0.2, 0.05), (0.3, 0.1, -0.4))
    T_model_arm = T_model_base @ pose((0, 0.05, 0.3), np.radians((20, -10, 45)))
    s, c = np.sin(np.pi / 8), np.cos(np.pi / 8)  # the quaternion: 45 degrees about y
    T_arm_joint = pose((0.02, 0, -0.1), (0, np.pi / 4, 0))
    np.testing.assert_allclose([0, s, 0, c], [0, 0.3826834, 0, 0.9238795], atol=1e-7)
    origin = (T_model_arm @ T_arm_joint)[:3, 3]
    for q in (0.0, 0.7, -1.3):
        expected = np.linalg.inv(T_model_base) @ about_line((0.6, 0, 0.8), origin, q) @ T_model_arm
        frames = model.link_frames_in_root(torch.tensor([[q]], dtype=torch.float64))
        np.testing.assert_allclose(frames[0, 1].numpy(), expected, atol=1e-7)


@pytest.mark.parametrize("change, message", [
    (("relative_to=\"base\"", "relative_to=\"nowhere\""), "frame 'nowhere' named by relative_to"),
    (("</model>", "<include><uri>model://other</uri></include></model>"), "a nested <include> is not supported"),
])
def test_sdf_frames_that_cannot_be_resolved_are_refused(tmp_path, change, message):
    (tmp_path / "bad.sdf").write_text(SDF_FRAMES.replace(*change))
    with pytest.raises(ConfigError, match=message):
        load_urdf_robot(tmp_path / "bad.sdf", "base")


def test_rotation_matrix_to_roll_pitch_yaw_round_trip():
    """``_matrix_to_rpy`` (a quaternion or degrees pose handed to the SDF reader as radians) inverts
    ``_rpy_to_matrix``, at gimbal lock too (the rotation, not the angles, is what must come back)."""
    from pipeline.robots.description import _matrix_to_rpy, _rpy_to_matrix

    rng = np.random.default_rng(3)
    angles = [rng.uniform(-np.pi, np.pi, 3) for _ in range(50)] + [(0.4, np.pi / 2, -1.0), (1.1, -np.pi / 2, 0.2)]
    for rpy in angles:
        R = _rpy_to_matrix(rpy)
        np.testing.assert_allclose(_rpy_to_matrix(_matrix_to_rpy(R)), R, atol=1e-12)


def test_sdf_1_4_axes_are_in_the_model_frame(tmp_path):
    """SDF 1.4 wrote a joint's axis in the model frame; 1.5+ in the joint frame unless use_parent_model_frame."""
    def arm_axis(text):
        (tmp_path / "a.sdf").write_text(text)
        model = load_urdf_robot(tmp_path / "a.sdf", "base")
        frames = model.link_frames_in_root(torch.tensor([[0.0], [0.5]], dtype=torch.float64))
        R = frames[1, 1, :3, :3] @ frames[0, 1, :3, :3].T  # the arm's rotation between q = 0 and 0.5, base frame
        return torch.tensor([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]).numpy() / (2 * np.sin(0.5))

    base_in_model = np.array([[np.cos(0.2), -np.sin(0.2), 0], [np.sin(0.2), np.cos(0.2), 0], [0, 0, 1]])
    arm_in_model = _rpy_to_matrix_test((0.3, -0.4, 0.5))
    in_model = SDF_TWO_LINKS.replace('version="1.6"', 'version="1.4"')
    np.testing.assert_allclose(arm_axis(in_model), base_in_model.T @ [0, 1, 0], atol=1e-9)
    in_joint = SDF_TWO_LINKS  # 1.6: the joint frame, here the arm's
    np.testing.assert_allclose(arm_axis(in_joint), base_in_model.T @ arm_in_model @ [0, 1, 0], atol=1e-9)
    parent_model = SDF_TWO_LINKS.replace("<xyz>0 1 0</xyz>", "<xyz>0 1 0</xyz><use_parent_model_frame>true"
                                                              "</use_parent_model_frame>")
    np.testing.assert_allclose(arm_axis(parent_model), base_in_model.T @ [0, 1, 0], atol=1e-9)


def _rpy_to_matrix_test(rpy):
    (cr, cp, cy), (sr, sp, sy) = np.cos(rpy), np.sin(rpy)
    return np.array([[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                     [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr], [-sp, cp * sr, cp * cr]])


BROKEN_MIMIC = """<robot name='hand'>
  <link name='base'><visual><geometry><box size='0.1 0.1 0.1'/></geometry></visual></link>
  <link name='arm'><visual><geometry><box size='0.05 0.05 0.2'/></geometry></visual></link>
  <link name='finger'><visual><geometry><box size='0.01 0.01 0.05'/></geometry></visual></link>
  <joint name='j1' type='revolute'><parent link='base'/><child link='arm'/><axis xyz='0 1 0'/>
    <limit lower='-1' upper='1' effort='1' velocity='1'/></joint>
  <joint name='f1' type='revolute'><parent link='base'/><child link='finger'/><axis xyz='1 0 0'/>
    <limit lower='-1' upper='1' effort='1' velocity='1'/><mimic joint='nope' multiplier='2'/></joint>
</robot>"""


def test_a_mimic_of_an_unknown_joint_is_refused_only_where_it_moves_a_rendered_link(tmp_path):
    path = tmp_path / "hand.urdf"
    path.write_text(BROKEN_MIMIC)
    with pytest.raises(ConfigError, match="joint 'f1' mimics unknown joint 'nope' .*exclude 'finger'"):
        load_urdf_robot(path, "base")
    model = load_urdf_robot(path, "base", exclude=("finger",))  # the finger not rendered: its joint is not needed
    assert model.joint_names == ("j1",) and model.link_names == ("base", "arm")


def test_root_defaults_to_the_top_link_in_every_format():
    """``load_robot(path)`` without a root: the link no joint has as its child (URDF), MJCF's ``world``."""
    urdf = load_urdf_robot(TOY_ARM)
    assert urdf.root == "base_link" and urdf.link_names == load_urdf_robot(TOY_ARM, "base_link").link_names
    mjcf = load_urdf_robot(TOY_ARM.with_suffix(".xml"))
    assert mjcf.root == "world"
    assert mjcf.link_names == urdf.link_names and mjcf.joint_names == urdf.joint_names
