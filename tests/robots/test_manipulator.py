"""Loading a URDF: which links are rendered, which joints need readings, and the error messages."""

import logging
from pathlib import Path

import pytest
import torch

from pipeline.errors import AssetError, ConfigError
from pipeline.robots import ManipulatorModel, load_urdf_robot

ROBOTS = Path(__file__).resolve().parents[2] / "models" / "robots"
TOY_ARM = ROBOTS / "toy_arm" / "toy_arm.urdf"
ARM_JOINTS = tuple(f"joint{i}" for i in range(1, 7))
FINGER_JOINTS = ("left_finger_joint", "right_finger_joint")
ALL_LINKS = ("base_link", "link1", "link2", "link3", "link4", "link5", "link6", "hand", "left_finger", "right_finger")


def test_whole_subtree_below_base():
    model = load_urdf_robot(TOY_ARM, "base_link")
    assert isinstance(model, ManipulatorModel)
    assert model.name == "toy_arm" and model.root == "base_link" and model.tip is None
    assert model.link_names == ALL_LINKS  # camera_mount and tcp have no geometry
    assert model.joint_names == ARM_JOINTS + FINGER_JOINTS
    assert model.frame_names == ALL_LINKS + ("camera_mount", "tcp")
    assert model.faces.dtype == torch.int64 and int(model.faces.max()) == model.verts_link.shape[0] - 1
    assert model.vert_link_index.unique().tolist() == list(range(len(ALL_LINKS)))
    torch.testing.assert_close(model.joint_lower[:2], torch.tensor([-2.9, -1.8], dtype=torch.float64))
    torch.testing.assert_close(model.joint_upper[-1], torch.tensor(0.04, dtype=torch.float64))


def test_root_inside_the_tree():
    model = load_urdf_robot(TOY_ARM, "link3")
    assert model.link_names == ALL_LINKS[3:]
    assert model.joint_names == ARM_JOINTS[3:] + FINGER_JOINTS


def test_tip_cuts_side_branches():
    model = load_urdf_robot(TOY_ARM, "link2", tip="left_finger")
    assert model.tip == "left_finger"
    assert model.link_names == ("link2", "link3", "link4", "link5", "link6", "hand", "left_finger")
    assert model.joint_names == ARM_JOINTS[2:] + ("left_finger_joint",)
    assert "right_finger" not in model.frame_names and "camera_mount" not in model.frame_names


def test_tip_keeps_subtree_below_tip():
    model = load_urdf_robot(TOY_ARM, "base_link", tip="hand")
    assert model.link_names == ALL_LINKS
    model = load_urdf_robot(TOY_ARM, "base_link", tip="tcp")  # a tip without geometry still gets a frame
    assert model.link_names == ALL_LINKS[:8] and model.frame_names[-1] == "tcp"
    assert model.joint_names == ARM_JOINTS


def test_exclude_removes_only_the_named_links():
    model = load_urdf_robot(TOY_ARM, "base_link", exclude=("hand", "right_finger"))
    assert model.link_names == ALL_LINKS[:7] + ("left_finger",)
    assert model.joint_names == ARM_JOINTS + ("left_finger_joint",)
    assert "hand" in model.frame_names  # still a frame on the way to the left finger
    assert "right_finger" not in model.frame_names  # its joint has no reading


def test_exclude_outside_selection_is_logged(caplog):
    with caplog.at_level(logging.WARNING, logger="pipeline.robots"):
        model = load_urdf_robot(TOY_ARM, "link4", exclude=("link1",))
    assert model.link_names[0] == "link4"
    assert "link1" in caplog.text and "not among the selected links" in caplog.text


@pytest.mark.parametrize(
    "kwargs,role,name",
    [
        ({"root": "nope"}, "root", "nope"),
        ({"root": "base_link", "tip": "gripper"}, "tip", "gripper"),
        ({"root": "base_link", "exclude": ("hand", "wrist")}, "exclude", "wrist"),
    ],
)
def test_unknown_link_lists_valid_links(kwargs, role, name):
    with pytest.raises(ConfigError) as err:
        load_urdf_robot(TOY_ARM, **kwargs)
    message = str(err.value)
    assert message.startswith(f"{role}: unknown link {name!r} in toy_arm.urdf; links: base_link, link1,")
    assert "camera_mount" in message and "tcp" in message


def test_exclude_must_be_a_sequence_of_names():
    with pytest.raises(ConfigError, match="exclude: expected a sequence of link names, got the string 'hand'"):
        load_urdf_robot(TOY_ARM, "base_link", exclude="hand")


def test_tip_not_below_root():
    with pytest.raises(ConfigError, match="tip: link 'link1' is not below root 'link3' in toy_arm.urdf; links below"):
        load_urdf_robot(TOY_ARM, "link3", tip="link1")


def test_nothing_to_render():
    with pytest.raises(ConfigError, match="nothing to render below root 'camera_mount' in toy_arm.urdf"):
        load_urdf_robot(TOY_ARM, "camera_mount")


def test_unknown_primitive():
    with pytest.raises(ConfigError, match="primitive: expected one of 'auto', 'collision', 'box', 'cylinder', 'hull', 'cad', got"):
        load_urdf_robot(TOY_ARM, "base_link", primitive="mesh")


def test_missing_urdf_names_the_file(tmp_path):
    missing = tmp_path / "missing_robot.urdf"
    with pytest.raises(AssetError, match="missing_robot.urdf not found"):
        load_urdf_robot(missing, "base_link")
    with pytest.raises(FileNotFoundError):  # AssetError is also a FileNotFoundError
        load_urdf_robot(missing, "base_link")


@pytest.mark.parametrize(
    "text,message",
    [
        ("<robot><link name='a'>", "broken.urdf: not valid XML"),
        ("<sdf><model/></sdf>", "broken.urdf: expected a <robot> root element, got <sdf>"),
        (
            "<robot xmlns:xacro='http://www.ros.org/wiki/xacro'><xacro:macro name='m'/><link name='a'/></robot>",
            "run xacro on it first",
        ),
        ("<robot><link name='a'/><link name='b'/></robot>", r"expected one root link .* got \['a', 'b'\]"),
        (
            "<robot><link name='a'/><joint name='j' type='fixed'><parent link='a'/><child link='c'/></joint></robot>",
            "joint 'j' names unknown child link 'c'",
        ),
        (
            "<robot><link name='a'><visual><geometry><box size='1 1'/></geometry></visual></link></robot>",
            r"broken.urdf: cannot be parsed .*link\[@name='a'\]/visual\[1\]/geometry.* Invalid vector length",
        ),
    ],
)
def test_malformed_urdf(tmp_path, text, message):
    path = tmp_path / "broken.urdf"
    path.write_text(text)
    with pytest.raises(ConfigError, match=message):
        load_urdf_robot(path, "a")


def test_unsupported_joint_type_on_the_way(tmp_path):
    path = tmp_path / "floating.urdf"
    path.write_text(TOY_ARM.read_text().replace('name="joint4" type="revolute"', 'name="joint4" type="floating"'))
    with pytest.raises(ConfigError, match="joint 'joint4' is of type 'floating'; supported on the way.*give a link "
                                          "below that joint as the root \\(its child: 'link4'\\)"):
        load_urdf_robot(path, "base_link")
    assert load_urdf_robot(path, "link4").joint_names[0] == "joint5"  # above root: irrelevant


def test_joint_vector_orders_by_joint_names():
    model = load_urdf_robot(TOY_ARM, "link4")
    readings = {"right_finger_joint": 0.01, "joint6": 0.6, "joint5": 0.5, "left_finger_joint": 0.02}
    q = model.joint_vector(readings)
    assert q.dtype == torch.float64
    torch.testing.assert_close(q, torch.tensor([0.5, 0.6, 0.02, 0.01], dtype=torch.float64))
    # joints of the URDF the model does not need (above root, fixed) are ignored
    q2 = model.joint_vector(readings | {"joint1": 1.0, "hand_joint": 0.0})
    torch.testing.assert_close(q2, q)


def test_joint_vector_errors():
    model = load_urdf_robot(TOY_ARM, "link4")
    with pytest.raises(ConfigError) as err:
        model.joint_vector({"joint5": 0.0, "joint7": 1.0})
    assert str(err.value) == (
        "unknown joint name(s) 'joint7' for toy_arm.urdf; "
        "expected readings for: joint5, joint6, left_finger_joint, right_finger_joint"
    )
    with pytest.raises(ConfigError, match="missing joint reading.* for joint6, right_finger_joint"):
        model.joint_vector({"joint5": 0.0, "left_finger_joint": 0.0})
    full = {"joint5": 0.0, "joint6": 0.0, "left_finger_joint": 0.0, "right_finger_joint": 0.0}
    with pytest.raises(ConfigError, match="joint 'joint6': expected a finite number, got nan"):
        model.joint_vector(full | {"joint6": float("nan")})
    with pytest.raises(ConfigError, match="joint 'joint6': expected a number, got 'abc'"):
        model.joint_vector(full | {"joint6": "abc"})


def test_joint_vector_zero_missing_and_limits_warn(caplog):
    model = load_urdf_robot(TOY_ARM, "link4")
    with caplog.at_level(logging.WARNING, logger="pipeline.robots"):
        q = model.joint_vector({"joint5": 2.5, "left_finger_joint": 0.01}, zero_missing=True)
    torch.testing.assert_close(q, torch.tensor([2.5, 0.0, 0.01, 0.0], dtype=torch.float64))
    assert "no reading for joint(s) joint6, right_finger_joint: set to 0" in caplog.text
    assert "joint 'joint5' = 2.5 is outside its URDF limits [-2, 2]" in caplog.text


def test_a_load_shows_its_progress_over_the_links_only_when_asked(monkeypatch, tmp_path):
    """``progress=True`` iterates the links' meshes (and the outline's) under a tqdm bar that waits
    ``LOAD_PROGRESS_DELAY_S`` before it appears (so a cached load shows none); ``progress=False`` makes none. The
    model is the same either way."""
    import pipeline.robots.manipulator as manipulator

    bars = []

    def recording_tqdm(iterable, **options):
        bars.append((options["desc"], list(iterable), options["delay"], options["leave"]))
        return iter(bars[-1][1])

    monkeypatch.setattr(manipulator, "tqdm", recording_tqdm)
    urdf = ROBOTS / "toy_arm_mesh" / "toy_arm_mesh.urdf"
    plain = manipulator.load_robot(urdf, "base_link", mesh_cache=tmp_path)
    assert bars == []
    shown = manipulator.load_robot(urdf, "base_link", exclude=("hand",), mesh_cache=tmp_path, progress=True)
    assert [bar[0] for bar in bars] == ["link meshes", "outline meshes"]  # the hulls, then their outline's meshes
    assert "hand" not in bars[0][1] and set(shown.link_names) < set(bars[0][1])  # every selected link, drawn or not
    assert bars[1][1] == list(shown.link_names)
    assert all(bar[2] == manipulator.LOAD_PROGRESS_DELAY_S > 0 and bar[3] is False for bar in bars)
    again = manipulator.load_robot(urdf, "base_link", mesh_cache=tmp_path, progress=True)
    torch.testing.assert_close(again.verts_link, plain.verts_link)
    torch.testing.assert_close(again.outline.verts_link, plain.outline.verts_link)
