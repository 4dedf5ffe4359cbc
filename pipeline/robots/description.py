"""Robot descriptions (URDF, MJCF, SDF) read into one form: links with their geometry elements, joints, and the
pytorch-kinematics chain whose FK drives the fit.

Convention:
    Every pose is ``T_<to>_<from>``, a ``(4, 4)`` homogeneous transform (column vectors, metres, radians). A
    joint's ``T_parent_child`` is the child frame in the parent frame at zero joint value; revolute joints rotate
    and prismatic joints translate along their unit axis given in the child frame. A mimic joint follows its
    master (``q = multiplier * q_master + offset``) and needs no reading of its own.

Formats (``docs/robot-descriptions.md``):

- **URDF** (``.urdf``): parsed by pytorch-kinematics' bundled ``urdf_parser_py``; links are URDF links, visual and
  collision elements as written (box, cylinder, sphere, mesh with scale; ``package://`` names resolved by
  :mod:`pipeline.robots.mesh_io`).
- **MJCF** (``.xml``, ``.mjcf``): compiled by ``mujoco.MjModel.from_xml_path``, so ``meshdir``, includes, mesh
  scale and ``compiler`` settings (degrees, ``eulerseq``, ...) are honoured; links are bodies, joints are hinge
  (revolute) and slide (prismatic) joints; geoms (box, capsule, cylinder, sphere, ellipsoid, mesh; planes and
  height fields skipped) are **collision** geoms where ``contype`` or ``conaffinity`` is non-zero and **visual**
  geoms where both are zero (the convention of MuJoCo Menagerie, robosuite and dm_control); mesh vertices come
  from the compiled model (scaled, in the geom frame). An unnamed body or joint is called ``body<i>`` /
  ``joint<i>`` by its MuJoCo index.
- **SDF** (``.sdf``): parsed by pytorch-kinematics' ``urdf_parser_py.sdf`` (one ``<model>``, its links' visual
  elements); the links' and joints' poses are resolved here from the XML (:class:`_SdfFrames`: ``relative_to``,
  a joint's own pose, axes ``expressed_in`` a frame or SDF 1.4's model frame), which that reader does not do.

The chain: :func:`_chain` builds one ``pytorch_kinematics.Chain`` (float64) from every format's frames; the FK is
its ``forward_kinematics_tensor``. It is built here, not by ``pk.build_chain_from_urdf`` / ``_mjcf`` / ``_sdf``,
because those builders (pytorch-kinematics 0.10.0) fall short in ways the tests name
(``tests/robots/test_description.py``): they round joint origins and axes to float32 (up to 1e-7 m off on Baxter
after ``.to(float64)``), crash on a one-link URDF, compile MJCF from a string (mesh files then fail to load) and
leave out the shift back of an MJCF joint placed away from its body's origin. Mimic joints are mapped by
:class:`Kinematics` (pytorch-kinematics treats them as independent joints).
"""

from __future__ import annotations

import contextlib
import copy
import logging
import math
import re
import xml.etree.ElementTree as ET
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from pipeline.checks import check_shape
from pipeline.errors import AssetError, ConfigError

__all__ = [
    "DESCRIPTION_FORMATS",
    "Geometry",
    "Joint",
    "Kinematics",
    "Link",
    "RobotDescription",
    "description_format",
    "read_description",
]

logger = logging.getLogger(__name__)

DESCRIPTION_FORMATS = ("urdf", "mjcf", "sdf")
#: Joint kinds a rendered link may hang from (others, e.g. floating, planar, ball, free, are rejected there).
MOVABLE_JOINTS = ("revolute", "prismatic")


@dataclass(frozen=True, eq=False)
class Geometry:
    """One geometry element of a link.

    Fields:
        kind: ``"box"``, ``"cylinder"``, ``"capsule"``, ``"sphere"``, ``"ellipsoid"`` or ``"mesh"``.
        size: box ``(x, y, z)`` full sides; cylinder and capsule ``(radius, length)`` (capsule: of its straight
            part); sphere ``(radius,)``; ellipsoid ``(rx, ry, rz)``; mesh: scale ``(x, y, z)``; metres.
        filename: a mesh file's name as written in the description (mesh elements that name a file).
        T_link_geom: ``(4, 4)`` the element's frame in its link frame.
        verts, faces: the mesh itself where the description carries it (MJCF, compiled): ``(V, 3)`` float64
            metres in the element's frame, ``(F, 3)`` int64; ``None`` otherwise.
    """

    kind: str
    size: tuple[float, ...]
    filename: str | None
    T_link_geom: np.ndarray
    verts: np.ndarray | None = None
    faces: np.ndarray | None = None


@dataclass(frozen=True)
class Link:
    name: str
    visuals: tuple[Geometry, ...]
    collisions: tuple[Geometry, ...]


@dataclass(frozen=True, eq=False)
class Joint:
    """A joint between two links. ``kind`` is ``"fixed"``, ``"revolute"`` (URDF ``continuous`` too),
    ``"prismatic"``, or the unsupported kind's own name (``"floating"``, ``"planar"``, ``"ball"``, ``"free"``,
    ``"multiple"`` for an MJCF body with several joints). ``axis`` is a unit ``(3,)`` vector in the child frame;
    ``T_parent_joint`` places the joint in the parent frame and ``T_joint_child`` the child in the joint frame
    (identity except for MJCF joints away from their body's origin): ``T_parent_child(q) = T_parent_joint @
    motion(q) @ T_joint_child``."""

    name: str
    kind: str
    parent: str
    child: str
    T_parent_joint: np.ndarray
    T_joint_child: np.ndarray
    axis: np.ndarray
    lower: float
    upper: float
    mimic: tuple[str, float, float] | None  # (master joint, multiplier, offset)


@dataclass(frozen=True, eq=False)
class RobotDescription:
    """A parsed robot description (picklable: plain data and a float64 ``pytorch_kinematics.Chain``).

    Fields:
        name: the robot's (model's) name.
        source: the file it was read from.
        format: one of ``DESCRIPTION_FORMATS``.
        links: link (MJCF: body) name -> :class:`Link`, parents before children.
        joints: joint name -> :class:`Joint`.
        chain: the pytorch-kinematics chain over every link (frame names = link names).
    """

    name: str
    source: str
    format: str
    links: dict[str, Link]
    joints: dict[str, Joint]
    chain: object

    @property
    def parent_joint(self) -> dict[str, Joint]:
        """Child link -> the joint above it."""
        return {joint.child: joint for joint in self.joints.values()}

    def children(self, link: str) -> list[Joint]:
        return [joint for joint in self.joints.values() if joint.parent == link]

    def subtree(self, link: str) -> list[str]:
        """``link`` and every link below it, depth first, children in document order."""
        below: dict[str, list[str]] = {name: [] for name in self.links}
        for joint in self.joints.values():
            below[joint.parent].append(joint.child)
        out, stack = [], [link]
        while stack:
            name = stack.pop()
            out.append(name)
            stack.extend(reversed(below[name]))
        return out

    def path(self, top: str, link: str) -> list[str]:
        """Links from ``top`` down to ``link`` (``link`` must be ``top`` or below it)."""
        parent_joint = self.parent_joint
        out = [link]
        while out[-1] != top:
            out.append(parent_joint[out[-1]].parent)
        return out[::-1]

    def master(self, joint: Joint) -> tuple[Joint, float, float]:
        """The independent joint driving ``joint`` and ``(multiplier, offset)``, following chains of mimics."""
        scale, offset, seen = 1.0, 0.0, {joint.name}
        while joint.mimic is not None:
            name, multiplier, add = joint.mimic
            if name not in self.joints:
                raise ConfigError(f"{Path(self.source).name}: joint {joint.name!r} mimics unknown joint {name!r} (fix "
                                  f"the description, or leave the links it moves out of the rendered ones: "
                                  f"exclude {joint.child!r} and the links below it, or choose another tip)")
            if name in seen:
                raise ConfigError(f"{Path(self.source).name}: mimic joints form a cycle: {', '.join(sorted(seen))}")
            seen.add(name)
            scale, offset = multiplier * scale, multiplier * offset + add
            joint = self.joints[name]
        return joint, scale, offset

    def movable_on_path(self, root: str, link: str) -> list[Joint]:
        """The non-fixed joints from ``root`` down to ``link``."""
        parent_joint = self.parent_joint
        joints = [parent_joint[child] for child in self.path(root, link)[1:]]
        return [joint for joint in joints if joint.kind != "fixed"]

    def joints_on_paths(self, root: str, links: Sequence[str]) -> list[str]:
        """Independent movable joints on the way from ``root`` to each of ``links``, in depth-first order.

        Raises:
            ConfigError: a joint of an unsupported kind on the way (the message names it and the valid kinds).
        """
        on_paths = {joint.name for target in links for joint in self.movable_on_path(root, target)}
        names: list[str] = []
        parent_joint = self.parent_joint
        for link in self.subtree(root)[1:]:
            joint = parent_joint[link]
            if joint.name not in on_paths:
                continue
            if joint.kind not in MOVABLE_JOINTS:
                raise ConfigError(
                    f"joint {joint.name!r} is of type {joint.kind!r}; supported on the way to rendered links: "
                    f"fixed, {', '.join(MOVABLE_JOINTS)} (URDF continuous too); for a robot on a moving base, give "
                    f"a link below that joint as the root (its child: {joint.child!r})"
                )
            master = self.master(joint)[0].name
            if master not in names:
                names.append(master)
        return names

    def reachable(self, root: str, link: str, joint_names: Sequence[str]) -> bool:
        """Whether FK reaches ``link`` from ``root`` with readings of ``joint_names`` only (not through a joint
        whose mimic names no joint)."""
        try:
            return all(
                joint.kind in MOVABLE_JOINTS and self.master(joint)[0].name in joint_names
                for joint in self.movable_on_path(root, link)
            )
        except ConfigError:
            return False


@dataclass(frozen=True, kw_only=True, eq=False)
class Kinematics:
    """FK of selected frames relative to one of them, on the description's pytorch-kinematics chain.

    Our joint vector ``q (B, J)`` (independent joints only) becomes the chain's ``th = q @ joint_matrix.T +
    joint_bias`` (mimic joints follow their masters, joints outside the selection stay at 0); the chain gives every
    frame in its own base; frame ``k`` here is ``chain frame chain_index[k]``, and poses are expressed in frame 0.

    Fields:
        chain: float64 ``pytorch_kinematics.Chain`` (CPU).
        frame_names: ``K`` frame (link) names, frame 0 first (the root).
        chain_index: ``(K,)`` int64 index of each frame in the chain's frame order.
        joint_matrix: ``(P, J)`` float64, P = the chain's joint parameters.
        joint_bias: ``(P,)`` float64 (mimic offsets).
    """

    chain: object
    frame_names: tuple[str, ...]
    chain_index: torch.Tensor
    joint_matrix: torch.Tensor
    joint_bias: torch.Tensor

    def __post_init__(self) -> None:
        check_shape(self.chain_index, (len(self.frame_names),), "chain_index")
        dims = check_shape(self.joint_matrix, ("P", None), "joint_matrix")
        check_shape(self.joint_bias, (dims["P"],), "joint_bias")

    def frame_poses(self, joint_angles: torch.Tensor) -> torch.Tensor:
        """Poses of all frames in frame 0.

        Args:
            joint_angles: ``(B, J)`` joint values, radians (revolute) or metres (prismatic), floating point.

        Returns:
            ``(B, K, 4, 4)`` ``T_root_frame`` in the order of ``frame_names``; dtype and device of
            ``joint_angles`` (the chain runs in float64 on the CPU; gradients flow through the conversion).
        """
        q = joint_angles.to(dtype=torch.float64, device="cpu")  # (B, J)
        th = q @ self.joint_matrix.T + self.joint_bias  # (B, P)
        T_base_all = self.chain.forward_kinematics_tensor(th)  # (N, B, 4, 4), every chain frame
        T_base = T_base_all[self.chain_index]  # (K, B, 4, 4)
        R0, t0 = T_base[0, :, :3, :3], T_base[0, :, :3, 3]  # (B, 3, 3), (B, 3)
        T_root_base = torch.zeros_like(T_base[0])  # (B, 4, 4), the rigid inverse of frame 0's pose
        T_root_base[:, :3, :3] = R0.transpose(-1, -2)
        T_root_base[:, :3, 3] = -(R0.transpose(-1, -2) @ t0[..., None])[..., 0]
        T_root_base[:, 3, 3] = 1.0
        poses = (T_root_base[None] @ T_base).transpose(0, 1)  # (B, K, 4, 4)
        return poses.to(dtype=joint_angles.dtype, device=joint_angles.device)


# ---------------------------------------------------------------------------------------------------------------
# Reading


def description_format(path: str | Path) -> str:
    """The format of a description file: by its suffix (``.urdf``, ``.sdf``; ``.mjcf``), else by its XML root
    element (``<robot>`` URDF, ``<mujoco>`` MJCF, ``<sdf>`` SDF).

    Raises:
        AssetError: the file does not exist or cannot be read.
        ConfigError: not XML, or none of the formats (the message lists them).
    """
    path = Path(path)
    if not path.is_file():
        raise AssetError(f"robot description {path} not found")
    by_suffix = {".urdf": "urdf", ".sdf": "sdf", ".mjcf": "mjcf"}
    if path.suffix.lower() in by_suffix:
        return by_suffix[path.suffix.lower()]
    tag = _xml_root(path).tag
    by_tag = {"robot": "urdf", "mujoco": "mjcf", "sdf": "sdf"}
    if tag not in by_tag:
        raise ConfigError(
            f"robot description {path.name}: root element <{tag}> is none of <robot> (URDF), <mujoco> (MJCF), "
            "<sdf> (SDF)"
        )
    return by_tag[tag]


def read_description(path: str | Path) -> RobotDescription:
    """Read a URDF, MJCF or SDF file (see the module docstring).

    Raises:
        AssetError: the file (or, for MJCF, a file it includes) is missing or unreadable.
        ConfigError: a malformed description; the message names the file and the element.
    """
    path = Path(path)
    kind = description_format(path)
    read = {"urdf": _read_urdf, "mjcf": _read_mjcf, "sdf": _read_sdf}[kind]
    name, links, joints = read(path)
    _check_tree(path, links, joints)
    return RobotDescription(
        name=name, source=str(path), format=kind, links=links, joints=joints, chain=_chain(links, joints)
    )


def _xml_root(path: Path) -> ET.Element:
    try:
        return ET.parse(path).getroot()
    except ET.ParseError as err:
        raise ConfigError(f"robot description {path.name}: not valid XML ({err})") from None
    except OSError as err:
        raise AssetError(f"robot description {path}: cannot be read ({err})") from None


#: Elements the fit never reads, dropped before ``urdf_parser_py`` parses a description: it refuses some that ROS
#: tools accept (a ``<texture/>`` without ``filename``, as iCub's and Romeo's URDFs have; PR2's ``<transmission>``
#: elements), and none of them changes a link, a joint or a geometry.
UNREAD_ELEMENTS = ("material", "transmission", "gazebo")


_SDF_PLACEHOLDER_INERTIAL = ("<inertial><mass>1</mass><inertia><ixx>1</ixx><ixy>0</ixy><ixz>0</ixz><iyy>1</iyy>"
                              "<iyz>0</iyz><izz>1</izz></inertia></inertial>")


def _parser_input(root: ET.Element, kind: str) -> bytes:
    """The description as ``urdf_parser_py`` gets it: without ``UNREAD_ELEMENTS`` and, for SDF, each
    ``<mesh><uri>`` written as the ``<mesh><filename>`` that its SDF reader expects (the SDF standard, which Gazebo's
    descriptions follow, names the file ``uri``; pytorch-kinematics 0.10.0 reads only ``filename``) and a
    placeholder ``<inertial>`` in each link without one, SDF's default ``<axis>`` (z) in each joint without one (both
    optional in SDF, required by that reader)."""
    root = copy.deepcopy(root)
    for parent in root.iter():
        for child in list(parent):
            if child.tag in UNREAD_ELEMENTS:
                parent.remove(child)
    if kind == "sdf":
        for mesh in root.iter("mesh"):
            uri = mesh.find("uri")
            if uri is not None and mesh.find("filename") is None:
                uri.tag = "filename"
        for pose in root.iter("pose"):  # a quaternion or degrees, as roll-pitch-yaw radians (its reader's only form)
            if pose.get("rotation_format", "euler_rpy") != "euler_rpy" or pose.get("degrees") is not None:
                T, _ = _SdfFrames.own_pose(pose, "", "pose")
                pose.text = " ".join(repr(float(v)) for v in (*T[:3, 3], *_matrix_to_rpy(T[:3, :3])))
                pose.attrib.pop("rotation_format", None)
                pose.attrib.pop("degrees", None)
        for model in root.iter("model"):
            for link in model.findall("link"):
                if link.find("inertial") is None:
                    link.append(ET.fromstring(_SDF_PLACEHOLDER_INERTIAL))
            for joint in model.findall("joint"):
                if joint.find("axis") is None:  # SDF's default axis
                    joint.append(ET.fromstring("<axis><xyz>0 0 1</xyz></axis>"))
    return ET.tostring(root)


@contextlib.contextmanager
def _parser_messages_logged() -> Iterator[None]:
    """Route ``urdf_parser_py``'s messages (``Unknown attribute ...``, written to stderr) to ``logging.debug``."""
    from pytorch_kinematics.urdf_parser_py import xml_reflection
    from pytorch_kinematics.urdf_parser_py.xml_reflection import core

    saved = core.on_error, xml_reflection.on_error

    def to_log(message: str) -> None:
        logger.debug("robot description parser: %s", message)

    core.on_error = xml_reflection.on_error = to_log
    try:
        yield
    finally:
        core.on_error, xml_reflection.on_error = saved


def _read_urdf(path: Path) -> tuple[str, dict[str, Link], dict[str, Joint]]:
    from pytorch_kinematics.urdf_parser_py.urdf import URDF

    root = _xml_root(path)
    if any("xacro" in (el.tag or "") for el in root.iter()):
        raise ConfigError(f"URDF file {path.name}: holds xacro macros; run xacro on it first to get a plain URDF")
    if root.tag != "robot":
        raise ConfigError(f"URDF file {path.name}: expected a <robot> root element, got <{root.tag}>")
    try:
        with _parser_messages_logged():
            robot = URDF.from_xml_string(_parser_input(root, "urdf"))
    except Exception as err:  # urdf_parser_py raises many types (AssertionError, ParseError, ValueError, ...)
        message = " ".join(str(err).split())
        raise ConfigError(f"URDF file {path.name}: cannot be parsed ({type(err).__name__}: {message})") from None
    where = path.name
    links: dict[str, Link] = {}
    for link in robot.links:
        if link.name in links:
            raise ConfigError(f"{where}: link {link.name!r} is defined twice")
        here = f"{where}, link {link.name!r}"
        visuals = tuple(g for g in (_urdf_geometry(v, here) for v in link.visuals) if g)
        collisions = tuple(g for g in (_urdf_geometry(c, here) for c in link.collisions) if g)
        links[link.name] = Link(link.name, visuals, collisions)
    joints: dict[str, Joint] = {}
    for joint in robot.joints:
        here = f"{where}, joint {joint.name!r}"
        if joint.name in joints:
            raise ConfigError(f"{where}: joint {joint.name!r} is defined twice")
        kind = {"continuous": "revolute"}.get(joint.type, joint.type)
        axis = _unit_axis(joint.axis if joint.axis is not None else (1.0, 0.0, 0.0), here, movable=kind != "fixed")
        lower, upper = -math.inf, math.inf
        if joint.limit is not None and joint.type != "continuous":
            lower, upper = float(joint.limit.lower or 0.0), float(joint.limit.upper or 0.0)
        mimic = None
        if joint.mimic is not None:
            multiplier = 1.0 if joint.mimic.multiplier is None else float(joint.mimic.multiplier)
            mimic = (joint.mimic.joint, multiplier, float(joint.mimic.offset or 0.0))
        joints[joint.name] = Joint(
            joint.name, kind, joint.parent, joint.child, _urdf_origin(joint.origin, here), np.eye(4), axis,
            lower, upper, mimic,
        )  # fmt: skip
    return robot.name or path.stem, links, joints


def _urdf_geometry(element, where: str) -> Geometry | None:
    from pytorch_kinematics.urdf_parser_py.urdf import Box, Cylinder, Mesh, Sphere

    shape = element.geometry
    T = _urdf_origin(element.origin, where)
    if isinstance(shape, Box):
        return Geometry("box", _numbers(shape.size, 3, where, "box size"), None, T)
    if isinstance(shape, Cylinder):
        return Geometry("cylinder", _numbers((shape.radius, shape.length), 2, where, "cylinder size"), None, T)
    if isinstance(shape, Sphere):
        return Geometry("sphere", _numbers((shape.radius,), 1, where, "sphere radius"), None, T)
    if isinstance(shape, Mesh):
        scale = (1.0, 1.0, 1.0) if shape.scale is None else shape.scale
        scale = _numbers([scale] if np.isscalar(scale) else scale, (1, 3), where, "mesh scale")
        if not shape.filename:
            raise ConfigError(f"{where}: <mesh> lacks the attribute 'filename'")
        return Geometry("mesh", scale * 3 if len(scale) == 1 else scale, shape.filename, T)
    if shape is not None:
        logger.warning("%s: geometry %s is not supported (box, cylinder, sphere, mesh): ignored",
                       where, type(shape).__name__)  # fmt: skip
    return None


def _urdf_origin(origin, where: str) -> np.ndarray:
    T = np.eye(4)
    if origin is not None:
        T[:3, :3] = _rpy_to_matrix(_numbers(origin.rpy or (0, 0, 0), 3, where, "origin rpy"))
        T[:3, 3] = _numbers(origin.xyz or (0, 0, 0), 3, where, "origin xyz")
    return T


def _rpy_to_matrix(rpy: Sequence[float]) -> np.ndarray:
    """Roll-pitch-yaw about fixed axes x, y, z (URDF, SDF) to ``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)``."""
    (cr, cp, cy), (sr, sp, sy) = np.cos(rpy), np.sin(rpy)
    return np.array(
        [[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
         [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
         [-sp, cp * sr, cp * cr]]
    )  # fmt: skip


def _matrix_to_rpy(R: np.ndarray) -> tuple[float, float, float]:
    """Roll, pitch, yaw with ``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)`` (the inverse of ``_rpy_to_matrix``)."""
    pitch = math.atan2(-R[2, 0], math.hypot(R[0, 0], R[1, 0]))
    if math.hypot(R[0, 0], R[1, 0]) < 1e-12:  # pitch +-90 degrees: roll taken as 0
        return 0.0, pitch, math.atan2(-R[0, 1], R[1, 1])
    return math.atan2(R[2, 1], R[2, 2]), pitch, math.atan2(R[1, 0], R[0, 0])


def _quat_to_matrix(wxyz: Sequence[float]) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    w, x, y, z = (float(v) for v in wxyz)
    return Rotation.from_quat([x, y, z, w]).as_matrix()


def _pose(R: np.ndarray, t: Sequence[float]) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def _unit_axis(axis: Sequence[float], where: str, *, movable: bool) -> np.ndarray:
    axis = np.array(_numbers(axis, 3, where, "axis"))
    norm = float(np.linalg.norm(axis))
    if norm == 0.0:
        if movable:
            raise ConfigError(f"{where}: axis is zero")
        return np.array([1.0, 0.0, 0.0])
    return axis / norm


def _numbers(values, count: int | tuple[int, ...], where: str, what: str) -> tuple[float, ...]:
    counts = (count,) if isinstance(count, int) else count
    try:
        out = tuple(float(v) for v in values)
    except (TypeError, ValueError):
        out = ()
    if len(out) not in counts or not all(math.isfinite(v) for v in out):
        want = " or ".join(map(str, counts))
        raise ConfigError(f"{where}: {what}: expected {want} finite numbers, got {values!r}")
    return out


def _read_mjcf(path: Path) -> tuple[str, dict[str, Link], dict[str, Joint]]:
    try:
        import mujoco
    except ImportError:
        raise ConfigError(
            f"MJCF file {path.name}: reading MJCF needs the 'mujoco' package (pip install mujoco)"
        ) from None
    try:
        m = mujoco.MjModel.from_xml_path(str(path))
    except Exception as err:  # mujoco raises ValueError with the XML element and line in the message
        message = str(err).strip().replace("\n", "; ")
        error = AssetError if "file" in message.lower() and "open" in message.lower() else ConfigError
        raise error(f"MJCF file {path.name}: {message}") from None

    def body_name(i: int) -> str:
        return m.body(i).name or f"body{i}"

    links: dict[str, Link] = {}
    joints: dict[str, Joint] = {}
    geom_type = mujoco.mjtGeom
    kinds = {int(mujoco.mjtJoint.mjJNT_HINGE): "revolute", int(mujoco.mjtJoint.mjJNT_SLIDE): "prismatic",
             int(mujoco.mjtJoint.mjJNT_BALL): "ball", int(mujoco.mjtJoint.mjJNT_FREE): "free"}  # fmt: skip
    for i in range(m.nbody):
        name = body_name(i)
        if name in links:
            raise ConfigError(f"MJCF file {path.name}: two bodies are called {name!r}")
        visuals, collisions = [], []
        for g in np.flatnonzero(m.geom_bodyid == i):
            geometry = _mjcf_geometry(m, int(g), geom_type, f"{path.name}, body {name!r}")
            if geometry is not None:
                collides = bool(m.geom_contype[g] or m.geom_conaffinity[g])
                (collisions if collides else visuals).append(geometry)
        links[name] = Link(name, tuple(visuals), tuple(collisions))
        if i == 0:
            continue
        T_parent_body = _pose(_quat_to_matrix(m.body_quat[i]), m.body_pos[i])
        count, first = int(m.body_jntnum[i]), int(m.body_jntadr[i])
        if count == 0:
            joint_name, kind, axis, T_joint, lower, upper = f"{name}_fixed", "fixed", np.eye(3)[0], np.eye(4), 0, 0
        else:
            j = first
            joint_name = m.joint(j).name or f"joint{j}"
            kind = kinds[int(m.jnt_type[j])] if count == 1 else "multiple"
            axis = _unit_axis(m.jnt_axis[j], f"{path.name}, joint {joint_name!r}", movable=True)
            T_joint = _pose(np.eye(3), m.jnt_pos[j])  # the joint's anchor in the body frame
            limited = bool(m.jnt_limited[j])
            lower, upper = (float(m.jnt_range[j][0]), float(m.jnt_range[j][1])) if limited else (-math.inf, math.inf)
        if joint_name in joints:
            raise ConfigError(f"MJCF file {path.name}: two joints are called {joint_name!r}")
        joints[joint_name] = Joint(
            joint_name, kind, body_name(int(m.body_parentid[i])), name, T_parent_body @ T_joint,
            np.linalg.inv(T_joint), axis, lower, upper, None,
        )  # fmt: skip
    model_name = getattr(m, "name", "") or path.stem
    return model_name, links, joints


def _mjcf_geometry(m, g: int, geom_type, where: str) -> Geometry | None:
    kind = int(m.geom_type[g])
    size = m.geom_size[g]
    T = _pose(_quat_to_matrix(m.geom_quat[g]), m.geom_pos[g])
    if kind == geom_type.mjGEOM_BOX:
        return Geometry("box", tuple(2.0 * float(s) for s in size), None, T)
    if kind == geom_type.mjGEOM_CYLINDER:
        return Geometry("cylinder", (float(size[0]), 2.0 * float(size[1])), None, T)
    if kind == geom_type.mjGEOM_CAPSULE:
        return Geometry("capsule", (float(size[0]), 2.0 * float(size[1])), None, T)
    if kind == geom_type.mjGEOM_SPHERE:
        return Geometry("sphere", (float(size[0]),), None, T)
    if kind == geom_type.mjGEOM_ELLIPSOID:
        return Geometry("ellipsoid", tuple(float(s) for s in size), None, T)
    if kind == geom_type.mjGEOM_MESH:
        mesh = int(m.geom_dataid[g])
        v0, nv = int(m.mesh_vertadr[mesh]), int(m.mesh_vertnum[mesh])
        f0, nf = int(m.mesh_faceadr[mesh]), int(m.mesh_facenum[mesh])
        verts = np.asarray(m.mesh_vert[v0 : v0 + nv], dtype=np.float64)
        faces = np.asarray(m.mesh_face[f0 : f0 + nf], dtype=np.int64)
        name = m.mesh(mesh).name or f"mesh{mesh}"
        return Geometry("mesh", (1.0, 1.0, 1.0), name, T, verts, faces)
    logger.debug("%s: geom %d of type %d (plane, height field, ...) skipped", where, g, kind)
    return None


def _read_sdf(path: Path) -> tuple[str, dict[str, Link], dict[str, Joint]]:
    from pytorch_kinematics.urdf_parser_py.sdf import SDF, Box, Cylinder, Mesh, Sphere

    root = _xml_root(path)
    if root.tag != "sdf":
        raise ConfigError(f"SDF file {path.name}: expected an <sdf> root element, got <{root.tag}>")
    try:
        with _parser_messages_logged():
            model = SDF.from_xml_string(_parser_input(root, "sdf")).model
    except Exception as err:  # urdf_parser_py raises many types
        message = " ".join(str(err).split())
        raise ConfigError(f"SDF file {path.name}: cannot be parsed ({type(err).__name__}: {message})") from None
    if model is None:
        raise ConfigError(f"SDF file {path.name}: no <model> element")

    def pose(values) -> np.ndarray:
        values = (0.0,) * 6 if values is None else _numbers(values, 6, path.name, "pose")
        return _pose(_rpy_to_matrix(values[3:]), values[:3])

    frames = _SdfFrames(root, path.name)
    links: dict[str, Link] = {}
    T_model_link = {}
    for link in model.links:
        T_model_link[link.name] = frames.in_model(link.name)
        elements = []
        for visual in link.visuals:
            shape, T = visual.geometry, pose(visual.pose)
            if isinstance(shape, Box):
                elements.append(Geometry("box", _numbers(shape.size, 3, path.name, "box size"), None, T))
            elif isinstance(shape, Cylinder):
                elements.append(Geometry("cylinder", (float(shape.radius), float(shape.length)), None, T))
            elif isinstance(shape, Sphere):
                elements.append(Geometry("sphere", (float(shape.radius),), None, T))
            elif isinstance(shape, Mesh):
                scale = (1.0, 1.0, 1.0) if shape.scale is None else _numbers(shape.scale, 3, path.name, "mesh scale")
                elements.append(Geometry("mesh", scale, shape.filename, T))
        links[link.name] = Link(link.name, tuple(elements), ())
    joints: dict[str, Joint] = {}
    for joint in model.joints:
        here = f"{path.name}, joint {joint.name!r}"
        kind = joint.type if joint.type in ("fixed", "revolute", "prismatic") else joint.type or "unknown"
        limit = getattr(joint.axis, "limit", None) if joint.axis is not None else None
        lower = float(limit.lower) if limit is not None and limit.lower is not None else -math.inf
        upper = float(limit.upper) if limit is not None and limit.upper is not None else math.inf
        axis = joint.axis.xyz if joint.axis is not None else (1.0, 0.0, 0.0)
        if joint.parent == "world" and "world" not in T_model_link:
            continue  # SDF's world is no link of the model: such a joint only fixes the model in the world
        for role, link in (("parent", joint.parent), ("child", joint.child)):
            if link not in T_model_link:
                raise ConfigError(f"{here}: names unknown {role} link {link!r}")
        T_child_joint = frames.joint_in_child(joint.name)  # the joint's frame; its axis is read in it
        T_parent_joint = np.linalg.inv(T_model_link[joint.parent]) @ T_model_link[joint.child] @ T_child_joint
        axis = frames.axis_in_joint(joint.name, np.asarray(_numbers(axis, 3, here, "axis"), dtype=np.float64))
        joints[joint.name] = Joint(
            joint.name, kind, joint.parent, joint.child, T_parent_joint, np.linalg.inv(T_child_joint),
            _unit_axis(axis, here, movable=kind != "fixed"), lower, upper, None,
        )  # fmt: skip
    return model.name or path.stem, links, joints


class _SdfFrames:
    """The poses of an SDF model's links and joints from its XML, which pytorch-kinematics' SDF reader does not
    resolve: a ``<pose relative_to="...">`` (SDF 1.7+; a link's default is the model frame, a joint's its child
    link), ``degrees="true"`` and ``rotation_format="quat_xyzw"``, a joint's own pose, and an axis ``<xyz
    expressed_in="...">`` (or SDF 1.5-1.6's ``<use_parent_model_frame>``; SDF 1.4's axes are in the model frame).
    A frame named by ``relative_to`` or ``expressed_in`` is the model (``__model__`` or its name), a link, a joint
    or a ``<frame>`` of the model, whose own pose is relative to its ``relative_to``, else its ``attached_to``,
    else the model.

    Raises (from the constructor or the lookups):
        ConfigError: nested models or ``<include>``, an unknown frame name, a cycle of ``relative_to``, a malformed
            pose.
    """

    MODEL = "__model__"

    def __init__(self, root: ET.Element, where: str) -> None:
        model = root.find("model")
        if model is None:
            raise ConfigError(f"SDF file {where}: no <model> element")
        for tag in ("model", "include"):
            if model.find(tag) is not None:
                raise ConfigError(f"SDF file {where}: a nested <{tag}> is not supported; merge it into one <model> "
                                  f"(e.g. `gz sdf -p` on its URDF)")
        self.where = where
        self.model_name = model.get("name", "")
        version = tuple(int(v) for v in re.findall(r"\d+", root.get("version", "1.6"))[:2]) or (1, 6)
        self.axis_default = self.MODEL if version < (1, 5) else ""  # SDF 1.4 wrote joint axes in the model frame
        self.elements: dict[str, tuple[ET.Element, str]] = {}  # name -> (element, default frame of its pose)
        self.joints: dict[str, ET.Element] = {}
        for frame in model.findall("frame"):  # links, then joints, take a name before frames
            self.elements[frame.get("name", "")] = (frame, frame.get("attached_to") or self.MODEL)
        for joint in model.findall("joint"):
            self.joints[joint.get("name", "")] = joint
            self.elements[joint.get("name", "")] = (joint, joint.findtext("child", "").strip())
        for link in model.findall("link"):
            self.elements[link.get("name", "")] = (link, self.MODEL)
            for part in (*link.findall("visual"), *link.findall("collision")):
                pose = part.find("pose")
                if pose is not None and (pose.get("relative_to") or "").strip() not in ("", link.get("name")):
                    raise ConfigError(f"SDF file {where}: link {link.get('name')!r}, {part.tag} {part.get('name')!r}: "
                                      f"a pose relative_to another frame than its link is not supported")
        self.cache: dict[str, np.ndarray] = {self.MODEL: np.eye(4)}

    def _own_pose(self, element: ET.Element, default: str) -> tuple[np.ndarray, str]:
        """``(T_frame_element, frame)``: the element's own ``<pose>`` and the frame it is relative to."""
        pose = element.find("pose")
        if pose is None:
            return np.eye(4), default
        return self.own_pose(pose, default, f"{self.where}, {element.tag} {element.get('name')!r}")

    @staticmethod
    def own_pose(pose: ET.Element, default: str, where: str) -> tuple[np.ndarray, str]:
        """``(T, frame)`` of a ``<pose>`` element: its transform and the frame it is relative to (``default``
        where it names none)."""
        values = _numbers((pose.text or "0 0 0 0 0 0").split(), (6, 7), where, "pose")
        form = pose.get("rotation_format", "euler_rpy")
        if form == "quat_xyzw" and len(values) == 7:
            x, y, z, w = values[3:]
            R = _quat_to_matrix((w, x, y, z))
        elif form == "euler_rpy" and len(values) == 6:
            angles = np.radians(values[3:]) if pose.get("degrees", "false").strip() in ("true", "1") else values[3:]
            R = _rpy_to_matrix(angles)
        else:
            raise ConfigError(f"{where}: <pose rotation_format={form!r}> with {len(values)} values: expected 6 "
                              f"(euler_rpy) or 7 (quat_xyzw)")
        frame = (pose.get("relative_to") or "").strip() or default
        return _pose(R, values[:3]), frame

    def in_model(self, name: str, seen: tuple[str, ...] = ()) -> np.ndarray:
        """``T_model_frame`` of a link, joint or frame (or the model itself)."""
        name = self.MODEL if name in ("", self.model_name) else name
        if name in self.cache:
            return self.cache[name]
        if name not in self.elements:
            raise ConfigError(f"SDF file {self.where}: frame {name!r} named by relative_to / expressed_in is not a "
                              f"link, joint or <frame> of the model")
        if name in seen:
            raise ConfigError(f"SDF file {self.where}: the poses' relative_to form a cycle: {' -> '.join(seen)}")
        T, frame = self._own_pose(*self.elements[name])
        self.cache[name] = self.in_model(frame, (*seen, name)) @ T
        return self.cache[name]

    def joint_in_child(self, name: str) -> np.ndarray:
        """``T_child_joint``: the joint's frame in its child link's frame (exactly its pose when relative to it)."""
        element = self.joints[name]
        child = element.findtext("child", "").strip()
        T, frame = self._own_pose(element, child)
        if frame == child:
            return T
        return np.linalg.inv(self.in_model(child)) @ self.in_model(frame) @ T

    def axis_in_joint(self, name: str, xyz: np.ndarray) -> np.ndarray:
        """The joint's axis in its own frame, from ``xyz`` as written (in the joint frame by default)."""
        axis = self.joints[name].find("axis")
        if axis is None:
            return xyz
        frame = (axis.find("xyz").get("expressed_in") or "").strip() if axis.find("xyz") is not None else ""
        parent_model_frame = (axis.findtext("use_parent_model_frame") or "").strip()
        if not frame and (parent_model_frame in ("true", "1") or (self.axis_default and not parent_model_frame)):
            frame = self.MODEL
        if not frame or frame == name:
            return xyz
        T_model_joint = self.in_model(self.joints[name].findtext("child", "").strip()) @ self.joint_in_child(name)
        return T_model_joint[:3, :3].T @ self.in_model(frame)[:3, :3] @ xyz


def _check_tree(path: Path, links: dict[str, Link], joints: dict[str, Joint]) -> None:
    where = path.name
    if not links:
        raise ConfigError(f"{where}: no links")
    children: set[str] = set()
    for joint in joints.values():
        for role, link in (("parent", joint.parent), ("child", joint.child)):
            if link not in links:
                raise ConfigError(f"{where}: joint {joint.name!r} names unknown {role} link {link!r}")
        if joint.child in children:
            raise ConfigError(f"{where}: link {joint.child!r} is the child of two joints (a closed kinematic loop, "
                              f"e.g. a four-bar linkage; only tree-shaped descriptions are supported)")
        children.add(joint.child)
    tops = [name for name in links if name not in children]
    if len(tops) != 1:
        raise ConfigError(f"{where}: expected one root link (a link no joint has as child), got {tops or 'none'}")
    below: dict[str, list[str]] = {name: [] for name in links}
    for joint in joints.values():
        below[joint.parent].append(joint.child)
    seen, stack = set(), [tops[0]]
    while stack:
        name = stack.pop()
        if name not in seen:
            seen.add(name)
            stack.extend(below[name])
    if len(seen) != len(links):
        raise ConfigError(f"{where}: some links are not connected to the root link {tops[0]!r}")


def _chain(links: dict[str, Link], joints: dict[str, Joint]):
    """The float64 pytorch-kinematics chain over every link (frame name = link name).

    An adapter over pytorch-kinematics 0.10.0's builders, which round origins to float32, crash on a one-link
    URDF and cannot place an MJCF joint away from its body origin (see the module docstring): the frames are
    built here from the parse, in float64, and handed to ``pk.Chain``. A joint's ``T_joint_child`` (MJCF) is
    folded into its children's offsets and into an extra fixed frame ``<link>`` below a ``<link>::joint`` frame.
    Joints of unsupported kinds become fixed frames (a rendered link below one is rejected before FK is used).
    """
    from pytorch_kinematics.chain import Chain
    from pytorch_kinematics.frame import Frame
    from pytorch_kinematics.frame import Joint as ChainJoint
    from pytorch_kinematics.frame import Link as ChainLink
    from pytorch_kinematics.transforms import Transform3d

    def transform(T: np.ndarray) -> Transform3d:
        return Transform3d(matrix=torch.from_numpy(np.ascontiguousarray(T)).to(torch.float64)[None])

    by_child = {joint.child: joint for joint in joints.values()}
    top = next(name for name in links if name not in by_child)

    def frame(name: str) -> Frame:
        joint = by_child.get(name)
        if joint is None:
            node = Frame(name, link=ChainLink(name, offset=transform(np.eye(4))), joint=ChainJoint(dtype=torch.float64))
        else:
            movable = joint.kind in MOVABLE_JOINTS
            node = Frame(
                name if np.array_equal(joint.T_joint_child, np.eye(4)) else f"{name}::joint",
                link=ChainLink(name, offset=transform(np.eye(4))),
                joint=ChainJoint(
                    joint.name, offset=transform(joint.T_parent_joint), joint_type=joint.kind if movable else "fixed",
                    axis=torch.from_numpy(joint.axis).to(torch.float64), dtype=torch.float64,
                ),
            )  # fmt: skip
            if node.name != name:  # the body frame below the joint frame
                shifted = Frame(
                    name, link=ChainLink(name, offset=transform(joint.T_joint_child)),
                    joint=ChainJoint(f"{name}::body", dtype=torch.float64),
                )  # fmt: skip
                shifted.children = [frame(child.child) for child in joints.values() if child.parent == name]
                node.children = [shifted]
                return node
        node.children = [frame(child.child) for child in joints.values() if child.parent == name]
        return node

    return Chain(frame(top), dtype=torch.float64)


def kinematics_for(
    description: RobotDescription, frames: Sequence[str], joint_names: Sequence[str]
) -> Kinematics:
    """:class:`Kinematics` of ``frames`` (the first one is the root) driven by readings of ``joint_names``."""
    chain = description.chain
    chain_joints = chain.get_joint_parameter_names()
    A = torch.zeros(len(chain_joints), len(joint_names), dtype=torch.float64)
    b = torch.zeros(len(chain_joints), dtype=torch.float64)
    for p, name in enumerate(chain_joints):
        try:
            master, scale, offset = description.master(description.joints[name])
        except ConfigError:  # a broken mimic off the rendered links' paths (those are checked by ``joints_on_paths``)
            continue  # held at 0, as every joint that drives no rendered link
        if master.name in joint_names:
            A[p, list(joint_names).index(master.name)] = scale
            b[p] = offset
    index = [chain.frame_to_idx[name] for name in frames]
    return Kinematics(
        chain=chain,
        frame_names=tuple(frames),
        chain_index=torch.tensor(index, dtype=torch.int64),
        joint_matrix=A,
        joint_bias=b,
    )

