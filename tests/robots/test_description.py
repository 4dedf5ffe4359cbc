"""FK of the URDF manipulator model against an independent numpy FK (written here from the XML) and
pytorch-kinematics; gradients, dtypes and pickling."""

import pickle
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
import torch

from pipeline.errors import ShapeError
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


def test_matches_pytorch_kinematics():
    pk = pytest.importorskip("pytorch_kinematics")
    chain = pk.build_chain_from_urdf(TOY_ARM.read_bytes()).to(dtype=torch.float64)
    model = load_urdf_robot(TOY_ARM, "base_link")
    assert list(model.joint_names) == chain.get_joint_parameter_names()
    q = _random_joints(model, 4, seed=2)
    expected = chain.forward_kinematics(q)
    ours = model.link_frames_in_root(q)
    for k, name in enumerate(model.frame_names):
        # pytorch-kinematics converts the URDF origins in float32
        torch.testing.assert_close(ours[:, k], expected[name].get_matrix(), atol=1e-6, rtol=0)


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


def test_pickle_round_trip():
    model = load_urdf_robot(TOY_ARM, "base_link", tip="left_finger")
    copy = pickle.loads(pickle.dumps(model))
    q = _random_joints(model, 2, seed=6)
    torch.testing.assert_close(copy.mesh_in_root(q), model.mesh_in_root(q))
    assert copy.link_names == model.link_names and copy.joint_names == model.joint_names
