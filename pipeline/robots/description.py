"""URDF robot descriptions: parsing links, joints and geometry elements, and batched differentiable FK.

Convention:
    Every pose is ``T_root_<frame>``, a ``(4, 4)`` homogeneous transform that maps points in ``<frame>`` to the
    frame of the user's ``root`` link (column vectors, metres, radians). URDF conventions otherwise: a joint's
    origin is ``T_parent_child`` at zero joint value, ``rpy`` is roll-pitch-yaw about fixed axes
    (``R = Rz(yaw) Ry(pitch) Rx(roll)``), revolute joints rotate and prismatic joints translate along their unit
    axis given in the child frame, ``continuous`` is revolute without limits. A mimic joint follows its master
    (``q = multiplier * q_master + offset``) and needs no reading of its own.

FK is our own small batched implementation over the parsed URDF (plain tensors: device and dtype follow the
joint angles, float64 constants, picklable); the tests check it against pytorch-kinematics and an independent
numpy FK for every rendered link. ``floating`` and ``planar`` joints on the way to a rendered link are rejected.
"""

from __future__ import annotations

import logging
import math
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from pipeline.checks import check_shape
from pipeline.errors import AssetError, ConfigError, ShapeError

__all__ = ["Geometry", "Joint", "KinematicTree", "Link", "Robot", "kinematic_tree", "parse_urdf", "reachable"]

logger = logging.getLogger(__name__)

_FIXED, _REVOLUTE, _PRISMATIC = 0, 1, 2
JOINT_TYPES = {"fixed": _FIXED, "revolute": _REVOLUTE, "continuous": _REVOLUTE, "prismatic": _PRISMATIC}


@dataclass(frozen=True, kw_only=True, eq=False)
class KinematicTree:
    """Batched forward kinematics of a tree of frames below one top frame (plain tensors, picklable).

    Frame ``k`` sits in its parent's frame at ``T_parent_frame[k] @ motion_k(q)``, where ``motion_k`` rotates by
    (revolute) or translates along (prismatic) ``joint_axis[k]`` by ``joint_scale[k] * q[joint_index[k]] +
    joint_offset[k]``; fixed frames have index -1, scale 0 and offset 0. Frame 0 is the top (identity), parents
    come before their children.

    Fields:
        frame_names: ``K`` frame (link) names.
        parent_index: ``(K,)`` int64, index of the parent frame; -1 for the top.
        T_parent_frame: ``(K, 4, 4)`` float64, each frame in its parent at zero joint value (the joint origin).
        joint_type: ``(K,)`` int64: 0 fixed, 1 revolute, 2 prismatic.
        joint_axis: ``(K, 3)`` float64, unit axis in the frame itself (zero for fixed frames).
        joint_index: ``(K,)`` int64, which entry of the joint vector drives the frame (-1 for fixed frames).
        joint_scale: ``(K,)`` float64, 1 for a plain joint, the multiplier for a mimic joint, 0 if fixed.
        joint_offset: ``(K,)`` float64, 0 for a plain joint, the offset (rad or m) for a mimic joint.
    """

    frame_names: tuple[str, ...]
    parent_index: torch.Tensor
    T_parent_frame: torch.Tensor
    joint_type: torch.Tensor
    joint_axis: torch.Tensor
    joint_index: torch.Tensor
    joint_scale: torch.Tensor
    joint_offset: torch.Tensor

    def __post_init__(self) -> None:
        dims = check_shape(self.T_parent_frame, ("K", 4, 4), "T_parent_frame")
        for name in ("parent_index", "joint_type", "joint_index", "joint_scale", "joint_offset"):
            check_shape(getattr(self, name), (dims["K"],), name)
        check_shape(self.joint_axis, (dims["K"], 3), "joint_axis")
        if len(self.frame_names) != dims["K"]:
            raise ShapeError(f"frame_names: expected {dims['K']} names, got {len(self.frame_names)}")
        parents = self.parent_index.tolist()
        if parents[:1] != [-1] or any(not 0 <= p < k for k, p in enumerate(parents) if k > 0):
            raise ConfigError(f"parent_index: expected -1 then earlier frames only, got {parents}")

    def frame_poses(self, joint_angles: torch.Tensor) -> torch.Tensor:
        """Poses of all frames in the top frame.

        Args:
            joint_angles: ``(B, J)`` joint values, radians (revolute) or metres (prismatic), floating point.

        Returns:
            ``(B, K, 4, 4)`` ``T_top_frame`` in the order of ``frame_names``; dtype and device of ``joint_angles``.
        """
        like = {"dtype": joint_angles.dtype, "device": joint_angles.device}
        padded = torch.cat([joint_angles, joint_angles.new_zeros(joint_angles.shape[0], 1)], dim=1)  # (B, J + 1)
        q = padded[:, self.joint_index.to(joint_angles.device)]  # (B, K), fixed frames read the zero column
        q = q * self.joint_scale.to(**like) + self.joint_offset.to(**like)  # (B, K)
        is_revolute = (self.joint_type == _REVOLUTE).to(**like)[:, None]  # (K, 1)
        is_prismatic = (self.joint_type == _PRISMATIC).to(**like)[:, None]  # (K, 1)
        axis = self.joint_axis.to(**like)
        skew = _skew(axis * is_revolute)  # (K, 3, 3), zero unless revolute
        sin, cos = torch.sin(q)[..., None, None], torch.cos(q)[..., None, None]  # (B, K, 1, 1)
        R = torch.eye(3, **like) + sin * skew + (1.0 - cos) * (skew @ skew)  # (B, K, 3, 3), Rodrigues
        motion = torch.zeros(*q.shape, 4, 4, **like)  # (B, K, 4, 4)
        motion[..., :3, :3] = R
        motion[..., :3, 3] = q[..., None] * (axis * is_prismatic)  # (B, K, 3)
        motion[..., 3, 3] = 1.0
        local = self.T_parent_frame.to(**like) @ motion  # (B, K, 4, 4)
        poses = [local[:, 0]]
        for k, parent in enumerate(self.parent_index.tolist()[1:], start=1):
            poses.append(poses[parent] @ local[:, k])
        return torch.stack(poses, dim=1)  # (B, K, 4, 4)


@dataclass(frozen=True)
class Geometry:
    kind: str  # "box", "cylinder", "sphere" or "mesh"
    size: tuple[float, ...]  # box: (x, y, z); cylinder: (radius, length); sphere: (radius,); mesh: scale (x, y, z)
    filename: str | None  # mesh only
    T_link_geom: np.ndarray  # (4, 4) the element's origin in its link frame


@dataclass(frozen=True)
class Link:
    name: str
    visuals: tuple[Geometry, ...]
    collisions: tuple[Geometry, ...]


@dataclass(frozen=True)
class Joint:
    name: str
    kind: str
    parent: str
    child: str
    T_parent_child: np.ndarray  # (4, 4) the joint origin
    axis: np.ndarray  # (3,) unit
    lower: float
    upper: float
    mimic: tuple[str, float, float] | None  # (master joint, multiplier, offset)


@dataclass(frozen=True)
class Robot:
    name: str
    links: dict[str, Link]  # in document order
    joints: dict[str, Joint]  # in document order
    parent_joint: dict[str, Joint]  # child link -> the joint above it
    children: dict[str, list[Joint]]  # parent link -> joints below it, in document order

    def subtree(self, link: str) -> list[str]:
        """``link`` and every link below it, depth first, children in document order."""
        out = [link]
        for joint in self.children[link]:
            out += self.subtree(joint.child)
        return out

    def path(self, top: str, link: str) -> list[str]:
        """Links from ``top`` down to ``link`` (``link`` must be ``top`` or below it)."""
        out = [link]
        while out[-1] != top:
            out.append(self.parent_joint[out[-1]].parent)
        return out[::-1]

    def master(self, joint: Joint) -> tuple[Joint, float, float]:
        """The independent joint driving ``joint`` and ``(multiplier, offset)``, following chains of mimics."""
        scale, offset, seen = 1.0, 0.0, {joint.name}
        while joint.mimic is not None:
            name, multiplier, add = joint.mimic
            if name not in self.joints:
                raise ConfigError(f"joint {joint.name!r} mimics unknown joint {name!r}")
            if name in seen:
                raise ConfigError(f"mimic joints form a cycle: {', '.join(sorted(seen))}")
            seen.add(name)
            scale, offset = multiplier * scale, multiplier * offset + add
            joint = self.joints[name]
        return joint, scale, offset

    def joints_on_paths(self, root: str, links: Sequence[str]) -> list[str]:
        """Independent movable joints on the way from ``root`` to each of ``links``, in depth-first order."""
        on_paths = {link for target in links for link in self.path(root, target)[1:]}
        names: list[str] = []
        for link in self.subtree(root)[1:]:
            joint = self.parent_joint[link]
            if link not in on_paths or joint.kind == "fixed":
                continue
            if joint.kind not in JOINT_TYPES:
                raise ConfigError(
                    f"joint {joint.name!r} is of type {joint.kind!r}; supported on the way to rendered links: "
                    f"{', '.join(JOINT_TYPES)}"
                )
            master = self.master(joint)[0].name
            if master not in names:
                names.append(master)
        return names



def reachable(robot: Robot, root: str, link: str, joint_names: Sequence[str]) -> bool:
    """Whether FK reaches ``link`` from ``root`` with readings of ``joint_names`` only."""
    for child in robot.path(root, link)[1:]:
        joint = robot.parent_joint[child]
        if joint.kind != "fixed" and (joint.kind not in JOINT_TYPES or robot.master(joint)[0].name not in joint_names):
            return False
    return True


def kinematic_tree(robot: Robot, frames: list[str], joint_names: list[str]) -> KinematicTree:
    parent_index, T_parent_frame, joint_type, axis, joint_index, joint_scale, joint_offset = [], [], [], [], [], [], []
    for k, link in enumerate(frames):
        joint = robot.parent_joint[link] if k > 0 else None
        parent_index.append(frames.index(joint.parent) if joint else -1)
        T_parent_frame.append(joint.T_parent_child if joint else np.eye(4))
        if joint is None or joint.kind == "fixed":
            row = (_FIXED, np.zeros(3), -1, 0.0, 0.0)
        else:
            master, scale, offset = robot.master(joint)
            row = (JOINT_TYPES[joint.kind], joint.axis, joint_names.index(master.name), scale, offset)
        for column, value in zip((joint_type, axis, joint_index, joint_scale, joint_offset), row):
            column.append(value)
    return KinematicTree(
        frame_names=tuple(frames),
        parent_index=torch.tensor(parent_index, dtype=torch.int64),
        T_parent_frame=torch.from_numpy(np.stack(T_parent_frame)).to(torch.float64),
        joint_type=torch.tensor(joint_type, dtype=torch.int64),
        joint_axis=torch.from_numpy(np.stack(axis)).to(torch.float64),
        joint_index=torch.tensor(joint_index, dtype=torch.int64),
        joint_scale=torch.tensor(joint_scale, dtype=torch.float64),
        joint_offset=torch.tensor(joint_offset, dtype=torch.float64),
    )



def parse_urdf(path: Path) -> Robot:
    if not path.is_file():
        raise AssetError(f"URDF file {path} not found")
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as err:
        raise ConfigError(f"URDF file {path.name}: not valid XML ({err})") from None
    except OSError as err:
        raise AssetError(f"URDF file {path}: cannot be read ({err})") from None
    if any("xacro" in (el.tag or "") for el in root.iter()):
        raise ConfigError(f"URDF file {path.name}: holds xacro macros; run xacro on it first to get a plain URDF")
    if root.tag != "robot":
        raise ConfigError(f"URDF file {path.name}: expected a <robot> root element, got <{root.tag}>")
    where = path.name

    links: dict[str, Link] = {}
    for el in root.findall("link"):
        name = _attr(el, "name", where)
        if name in links:
            raise ConfigError(f"{where}: link {name!r} is defined twice")
        visuals = tuple(g for g in (_geometry(v, f"{where}, link {name!r}") for v in el.findall("visual")) if g)
        collisions = tuple(g for g in (_geometry(c, f"{where}, link {name!r}") for c in el.findall("collision")) if g)
        links[name] = Link(name, visuals, collisions)
    if not links:
        raise ConfigError(f"{where}: no <link> elements")

    joints: dict[str, Joint] = {}
    parent_joint: dict[str, Joint] = {}
    children: dict[str, list[Joint]] = {name: [] for name in links}
    for el in root.findall("joint"):
        joint = _joint(el, where)
        if joint.name in joints:
            raise ConfigError(f"{where}: joint {joint.name!r} is defined twice")
        for role, link in (("parent", joint.parent), ("child", joint.child)):
            if link not in links:
                raise ConfigError(f"{where}: joint {joint.name!r} names unknown {role} link {link!r}")
        if joint.child in parent_joint:
            raise ConfigError(f"{where}: link {joint.child!r} is the child of two joints")
        joints[joint.name] = joint
        parent_joint[joint.child] = joint
        children[joint.parent].append(joint)
    tops = [name for name in links if name not in parent_joint]
    if len(tops) != 1:
        raise ConfigError(f"{where}: expected one root link (a link no joint has as child), got {tops or 'none'}")
    robot = Robot(root.get("name", path.stem), links, joints, parent_joint, children)
    if len(robot.subtree(tops[0])) != len(links):
        raise ConfigError(f"{where}: some links are not connected to the root link {tops[0]!r}")
    return robot


def _joint(el: ET.Element, where: str) -> Joint:
    name = _attr(el, "name", where)
    where = f"{where}, joint {name!r}"
    kind = _attr(el, "type", where)
    parent = _attr(_child(el, "parent", where), "link", where)
    child = _attr(_child(el, "child", where), "link", where)
    axis_el = el.find("axis")
    axis = np.array(_floats(axis_el.get("xyz", "1 0 0") if axis_el is not None else "1 0 0", 3, where, "axis"))
    if kind in ("revolute", "continuous", "prismatic"):
        norm = float(np.linalg.norm(axis))
        if norm == 0.0:
            raise ConfigError(f"{where}: axis is zero")
        axis = axis / norm
    lower, upper = -math.inf, math.inf
    limit = el.find("limit")
    if limit is not None and kind != "continuous":
        lower = _floats(limit.get("lower", "0"), 1, where, "limit lower")[0]
        upper = _floats(limit.get("upper", "0"), 1, where, "limit upper")[0]
    mimic_el = el.find("mimic")
    mimic = None
    if mimic_el is not None:
        mimic = (
            _attr(mimic_el, "joint", where),
            _floats(mimic_el.get("multiplier", "1"), 1, where, "mimic multiplier")[0],
            _floats(mimic_el.get("offset", "0"), 1, where, "mimic offset")[0],
        )
    return Joint(name, kind, parent, child, _origin(el, where), axis, lower, upper, mimic)


def _geometry(el: ET.Element, where: str) -> Geometry | None:
    geometry = el.find("geometry")
    if geometry is None or len(geometry) == 0:
        return None
    shape = geometry[0]
    T = _origin(el, where)
    if shape.tag == "box":
        return Geometry("box", _floats(_attr(shape, "size", where), 3, where, "box size"), None, T)
    if shape.tag == "cylinder":
        radius = _floats(_attr(shape, "radius", where), 1, where, "cylinder radius")[0]
        length = _floats(_attr(shape, "length", where), 1, where, "cylinder length")[0]
        return Geometry("cylinder", (radius, length), None, T)
    if shape.tag == "sphere":
        return Geometry("sphere", _floats(_attr(shape, "radius", where), 1, where, "sphere radius"), None, T)
    if shape.tag == "mesh":
        scale = _floats(shape.get("scale", "1 1 1"), (1, 3), where, "mesh scale")
        return Geometry("mesh", scale * 3 if len(scale) == 1 else scale, _attr(shape, "filename", where), T)
    logger.warning("%s: geometry <%s> is not supported (box, cylinder, sphere, mesh): ignored", where, shape.tag)
    return None


def _origin(el: ET.Element, where: str) -> np.ndarray:
    origin = el.find("origin")
    T = np.eye(4)
    if origin is not None:
        T[:3, :3] = _rpy_to_matrix(_floats(origin.get("rpy", "0 0 0"), 3, where, "origin rpy"))
        T[:3, 3] = _floats(origin.get("xyz", "0 0 0"), 3, where, "origin xyz")
    return T


def _rpy_to_matrix(rpy: Sequence[float]) -> np.ndarray:
    """URDF roll-pitch-yaw (fixed axes x, y, z) to ``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)``."""
    (cr, cp, cy), (sr, sp, sy) = np.cos(rpy), np.sin(rpy)
    return np.array(
        [[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
         [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
         [-sp, cp * sr, cp * cr]]
    )  # fmt: skip


def _attr(el: ET.Element, name: str, where: str) -> str:
    value = el.get(name)
    if value is None:
        raise ConfigError(f"{where}: <{el.tag}> lacks the attribute {name!r}")
    return value


def _child(el: ET.Element, tag: str, where: str) -> ET.Element:
    found = el.find(tag)
    if found is None:
        raise ConfigError(f"{where}: <{el.tag}> lacks a <{tag}> element")
    return found


def _floats(text: str, count: int | tuple[int, ...], where: str, what: str) -> tuple[float, ...]:
    counts = (count,) if isinstance(count, int) else count
    try:
        values = tuple(float(v) for v in text.split())
    except ValueError:
        values = ()
    if len(values) not in counts or not all(math.isfinite(v) for v in values):
        want = " or ".join(map(str, counts))
        raise ConfigError(f"{where}: {what}: expected {want} finite numbers, got {text!r}")
    return values



def _skew(axis: torch.Tensor) -> torch.Tensor:
    """``(K, 3)`` vectors to ``(K, 3, 3)`` cross-product matrices."""
    x, y, z = axis.unbind(-1)
    zero = torch.zeros_like(x)
    return torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], dim=-1).reshape(*axis.shape[:-1], 3, 3)

