"""Rigid manipulators from URDF: the rendered links, their primitive meshes, and batched differentiable FK.

Convention:
    Every pose is ``T_root_<frame>``, a ``(4, 4)`` homogeneous transform that maps points in ``<frame>`` to the
    frame of the user's ``root`` link (column vectors, metres, radians). URDF conventions otherwise: a joint's
    origin is ``T_parent_child`` at zero joint value, ``rpy`` is roll-pitch-yaw about fixed axes
    (``R = Rz(yaw) Ry(pitch) Rx(roll)``), revolute joints rotate and prismatic joints translate along their unit
    axis given in the child frame, ``continuous`` is revolute without limits.

Which links are rendered (DESIGN.md 4): the subtree below ``root`` (with ``tip``: the chain from ``root`` down to
``tip`` plus the subtree below ``tip``), minus the links named in ``exclude`` (only those links, not their
children), minus links without geometry. Only the movable joints on the way from ``root`` to a rendered link (or
to ``tip``) need a reading; they are ``ManipulatorModel.joint_names``. A mimic joint follows its master
(``q = multiplier * q_master + offset``) and needs no reading of its own.

Geometry per rendered link, by ``primitive`` (a link's geometry is its collision elements, or its visual elements
where it has no collision element; for ``"cad"`` the other way round):

- ``"collision"``: each box, cylinder and sphere as a closed triangle mesh; a mesh element is replaced by the box
  bounding its vertices (in the element's frame).
- ``"box"`` / ``"cylinder"``: one primitive per link, sized by the bounding box of the link's geometry: in the
  element's own frame when the link has one element, else axis-aligned in the link frame. The cylinder's axis
  follows the longest side of that box (its z side on ties), its radius is half the larger of the two other sides.
  A link whose geometry is one box (one cylinder) keeps it as it is in ``"box"`` (``"cylinder"``) mode.
  ``primitive_size="volume"`` then scales the primitive about its centre to the volume of the link's geometry
  (the sum of its elements' volumes, overlaps counted twice; a mesh element that is not closed leaves the link at
  its bounding size, with a warning): a primitive around a link covers more of the image than the link does, and
  the pose fit pays that back in depth (README, "Manipulator pose").
- ``"cad"``: the visual meshes loaded with trimesh (``package://`` and relative file names resolved, see
  :func:`resolve_mesh_path`), scaled as the URDF says; primitive visual elements meshed as in ``"collision"``.

Primitive meshes come from :mod:`pipeline.shapes.primitives` (subdivided, watertight, outward winding).

FK is our own small batched implementation over the parsed URDF (plain tensors: device and dtype follow the
joint angles, float64 constants, picklable); the tests check it against pytorch-kinematics and an independent
numpy FK for every rendered link.

Limitations: ``floating`` and ``planar`` joints on the way to a rendered link are rejected; mesh files are read
by trimesh (STL, OBJ, PLY, ...; COLLADA ``.dae`` needs the optional ``pycollada`` package); the CAD meshes are
used at full resolution.
"""

from __future__ import annotations

import logging
import math
import xml.etree.ElementTree as ET
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from pipeline.checks import check_choice, check_shape
from pipeline.errors import AssetError, ConfigError, ShapeError
from pipeline.shapes.primitives import box_mesh, cylinder_mesh, sphere_mesh

__all__ = ["PRIMITIVE_CHOICES", "KinematicTree", "ManipulatorModel", "load_urdf_robot", "resolve_mesh_path"]

logger = logging.getLogger(__name__)

PRIMITIVE_CHOICES = ("collision", "box", "cylinder", "cad")
PRIMITIVE_SIZE_CHOICES = ("bbox", "volume")

_FIXED, _REVOLUTE, _PRISMATIC = 0, 1, 2
_JOINT_TYPES = {"fixed": _FIXED, "revolute": _REVOLUTE, "continuous": _REVOLUTE, "prismatic": _PRISMATIC}


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


@dataclass(frozen=True, kw_only=True, eq=False)
class ManipulatorModel:
    """A rigid manipulator as rendered: link meshes in their link frames, and FK from joint values to the root.

    Build it with :func:`load_urdf_robot`. Plain strings, tuples and tensors only (picklable, no open files).

    Fields:
        name: the URDF's robot name.
        urdf_path: the URDF file it was loaded from.
        root: the link whose frame every pose is expressed in.
        tip: the tip link that cut the rendered chain, or ``None`` for the whole subtree below ``root``.
        primitive: how link geometry was built, one of ``PRIMITIVE_CHOICES``.
        link_names: the ``L`` rendered links, parents before children.
        joint_names: the ``J`` joints that need a reading, in the order of the joint vector.
        joint_lower, joint_upper: ``(J,)`` float64 limits (rad or m; +-inf where the URDF gives none).
        urdf_joint_names: every joint of the URDF (readings for joints not needed are ignored).
        kinematics: FK of the frames below ``root``: the rendered links, ``tip``, and geometry-less links that
            need no further readings (e.g. a camera mount); frame 0 is ``root``.
        link_frame_index: ``(L,)`` int64, frame index in ``kinematics`` of each rendered link.
        verts_link: ``(V, 3)`` float64 vertices, metres, each in its own link's frame.
        faces: ``(F, 3)`` int64 triangles indexing ``verts_link``, counter-clockwise seen from outside.
        vert_link_index: ``(V,)`` int64, the rendered link (index into ``link_names``) of each vertex;
            non-decreasing (each link's vertices are one block).
    """

    name: str
    urdf_path: str
    root: str
    tip: str | None
    primitive: str
    link_names: tuple[str, ...]
    joint_names: tuple[str, ...]
    joint_lower: torch.Tensor
    joint_upper: torch.Tensor
    urdf_joint_names: tuple[str, ...]
    kinematics: KinematicTree
    link_frame_index: torch.Tensor
    verts_link: torch.Tensor
    faces: torch.Tensor
    vert_link_index: torch.Tensor

    def __post_init__(self) -> None:
        check_choice(self.primitive, PRIMITIVE_CHOICES, "primitive")
        J, L = len(self.joint_names), len(self.link_names)
        check_shape(self.joint_lower, (J,), "joint_lower")
        check_shape(self.joint_upper, (J,), "joint_upper")
        check_shape(self.link_frame_index, (L,), "link_frame_index")
        dims = check_shape(self.verts_link, ("V", 3), "verts_link")
        check_shape(self.faces, (None, 3), "faces")
        check_shape(self.vert_link_index, (dims["V"],), "vert_link_index")
        if dims["V"] and not bool((self.vert_link_index.diff() >= 0).all()):
            raise ConfigError("vert_link_index: expected each link's vertices as one block (non-decreasing)")
        if self.kinematics.frame_names[0] != self.root:
            raise ConfigError(f"kinematics: expected frame 0 to be the root {self.root!r}")
        if not bool(((self.kinematics.joint_index >= -1) & (self.kinematics.joint_index < J)).all()):
            raise ConfigError(f"kinematics: joint_index must lie in [-1, {J}) for the joints {self.joint_names}")

    @property
    def frame_names(self) -> tuple[str, ...]:
        """Names of the frames :meth:`link_frames_in_root` returns (``root`` first)."""
        return self.kinematics.frame_names

    def frame_index(self, name: str) -> int:
        """Index of a frame in :attr:`frame_names`; ``ConfigError`` listing them if ``name`` is not one."""
        if name not in self.frame_names:
            raise ConfigError(f"frame {name!r} is not in the model; frames: {', '.join(self.frame_names)}")
        return self.frame_names.index(name)

    def joint_vector(self, joint_values: Mapping[str, float], *, zero_missing: bool = False) -> torch.Tensor:
        """Joint readings by name to the joint vector.

        Names of URDF joints the model does not need (fixed, mimic, outside the rendered links) are ignored.

        Args:
            joint_values: joint name -> value, radians (revolute) or metres (prismatic).
            zero_missing: set joints without a reading to 0 (with a logged warning) instead of raising.

        Returns:
            ``(J,)`` float64 in the order of ``joint_names``.

        Raises:
            ConfigError: a name that is no joint of the URDF, a missing reading (unless ``zero_missing``), or a
                value that is not a finite number; the message lists the expected or the missing names.
        """
        unknown = [n for n in joint_values if n not in self.urdf_joint_names]
        if unknown:
            raise ConfigError(
                f"unknown joint name(s) {', '.join(map(repr, unknown))} for {Path(self.urdf_path).name}; "
                f"expected readings for: {', '.join(self.joint_names)}"
            )
        missing = [n for n in self.joint_names if n not in joint_values]
        if missing and not zero_missing:
            raise ConfigError(
                f"missing joint reading(s) for {', '.join(missing)} (every movable joint on the way from "
                f"root {self.root!r} to a rendered link needs a value)"
            )
        if missing:
            logger.warning("no reading for joint(s) %s: set to 0", ", ".join(missing))
        ignored = [n for n in joint_values if n not in self.joint_names]
        if ignored:
            logger.debug("readings not needed by the rendered links, ignored: %s", ", ".join(ignored))
        values = []
        for name in self.joint_names:
            raw = joint_values.get(name, 0.0)
            try:
                value = float(raw)
            except (TypeError, ValueError):
                raise ConfigError(f"joint {name!r}: expected a number, got {raw!r}") from None
            if not math.isfinite(value):
                raise ConfigError(f"joint {name!r}: expected a finite number, got {raw!r}")
            values.append(value)
        q = torch.tensor(values, dtype=torch.float64)
        outside = (q < self.joint_lower) | (q > self.joint_upper)
        for i in torch.nonzero(outside).flatten().tolist():
            logger.warning(
                "joint %r = %g is outside its URDF limits [%g, %g]",
                self.joint_names[i], values[i], float(self.joint_lower[i]), float(self.joint_upper[i]),
            )  # fmt: skip
        return q

    def link_frames_in_root(self, joint_angles: torch.Tensor) -> torch.Tensor:
        """Poses of every frame of :attr:`frame_names` (rendered links, tip, mounts) in the root frame.

        Args:
            joint_angles: ``(B, J)`` joint values in the order of ``joint_names``, rad or m.

        Returns:
            ``(B, K, 4, 4)`` ``T_root_frame``; dtype and device of ``joint_angles``.
        """
        check_shape(joint_angles, (None, len(self.joint_names)), "joint_angles")
        if not joint_angles.is_floating_point():
            raise ShapeError(f"joint_angles: expected a floating point tensor, got {joint_angles.dtype}")
        return self.kinematics.frame_poses(joint_angles)

    def link_poses(self, joint_angles: torch.Tensor) -> torch.Tensor:
        """Poses of the rendered links in the root frame.

        Args:
            joint_angles: ``(B, J)`` joint values in the order of ``joint_names``, rad or m.

        Returns:
            ``(B, L, 4, 4)`` ``T_root_link`` in the order of ``link_names``; dtype and device of ``joint_angles``.
        """
        frames = self.link_frames_in_root(joint_angles)  # (B, K, 4, 4)
        return frames[:, self.link_frame_index.to(joint_angles.device)]

    def mesh_in_root(self, joint_angles: torch.Tensor, vertex_offsets: torch.Tensor | None = None) -> torch.Tensor:
        """Vertices of the robot mesh in the root frame: ``v = T_root_link(q) @ (v_link + v_offset)``.

        Differentiable with respect to ``joint_angles`` and ``vertex_offsets``. Faces are :attr:`faces`.

        Args:
            joint_angles: ``(B, J)`` joint values in the order of ``joint_names``, rad or m.
            vertex_offsets: ``(B, V, 3)`` per-vertex offsets in each vertex's link frame, metres, or ``None`` for
                none (the primitives as they are).

        Returns:
            ``(B, V, 3)`` vertices in the root frame, metres; dtype and device of ``joint_angles``.
        """
        T = self.link_poses(joint_angles)  # (B, L, 4, 4)
        verts = self.verts_link.to(dtype=joint_angles.dtype, device=joint_angles.device)[None]  # (1, V, 3)
        if vertex_offsets is not None:
            check_shape(vertex_offsets, (joint_angles.shape[0], self.verts_link.shape[0], 3), "vertex_offsets")
            verts = verts + vertex_offsets  # (B, V, 3)
        counts = torch.bincount(self.vert_link_index, minlength=len(self.link_names)).tolist()
        moved = []
        for i, block in enumerate(torch.split(verts, counts, dim=1)):  # block: (B or 1, V_l, 3), link i's vertices
            R, t = T[:, i, :3, :3], T[:, i, :3, 3]  # (B, 3, 3), (B, 3)
            moved.append(block @ R.transpose(-1, -2) + t[:, None])  # (B, V_l, 3)
        return torch.cat(moved, dim=1)  # (B, V, 3)


def load_urdf_robot(
    urdf_path: str | Path,
    root: str,
    *,
    tip: str | None = None,
    exclude: Sequence[str] = (),
    primitive: str = "collision",
    primitive_size: str = "bbox",
    package_map: Mapping[str, str | Path] | None = None,
) -> ManipulatorModel:
    """Load a URDF and build the rendered links' meshes and their FK (see the module docstring for the rules).

    Args:
        urdf_path: the ``.urdf`` file (plain URDF; run xacro first on ``.xacro`` files).
        root: link whose frame poses are expressed in (often the base link).
        tip: if given, render only the chain from ``root`` to ``tip`` plus the subtree below ``tip``; it must be
            ``root`` or below it.
        exclude: links not to render (only these links; their children stay).
        primitive: ``"collision"``, ``"box"``, ``"cylinder"`` or ``"cad"``.
        primitive_size: ``"box"`` / ``"cylinder"`` sizing: ``"bbox"`` (bounding, the default) or ``"volume"``
            (scaled to the volume of the link's geometry; see the module docstring).
        package_map: package name -> folder, for ``package://`` mesh names (see :func:`resolve_mesh_path`).

    Raises:
        AssetError: the URDF or a mesh file it needs is missing or unreadable.
        ConfigError: malformed URDF, unknown link names (the message lists the valid ones), ``tip`` not below
            ``root``, nothing to render, or an unsupported joint type on the way to a rendered link.
    """
    path = Path(urdf_path)
    check_choice(primitive, PRIMITIVE_CHOICES, "primitive")
    check_choice(primitive_size, PRIMITIVE_SIZE_CHOICES, "primitive_size")
    if isinstance(exclude, str):
        raise ConfigError(f"exclude: expected a sequence of link names, got the string {exclude!r}")
    robot = _parse_urdf(path)
    named = [("root", root)] + ([("tip", tip)] if tip is not None else []) + [("exclude", e) for e in exclude]
    for role, link in named:
        if link not in robot.links:
            raise ConfigError(f"{role}: unknown link {link!r} in {path.name}; links: {', '.join(robot.links)}")
    below_root = robot.subtree(root)
    if tip is None:
        selected = below_root
    elif tip not in below_root:
        raise ConfigError(
            f"tip: link {tip!r} is not below root {root!r} in {path.name}; links below root: {', '.join(below_root)}"
        )
    else:
        chain = set(robot.path(root, tip))
        tip_subtree = set(robot.subtree(tip))
        selected = [link for link in below_root if link in chain or link in tip_subtree]
    outside = [e for e in exclude if e not in selected]
    if outside:
        logger.warning("exclude: link(s) %s are not among the selected links anyway", ", ".join(outside))

    context = _MeshContext(urdf_dir=path.parent, package_map=dict(package_map or {}), cache={})
    link_meshes: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for link in selected:
        if link in exclude:
            continue
        mesh = _link_mesh(robot.links[link], primitive, context)
        if mesh is not None and primitive in ("box", "cylinder") and primitive_size == "volume":
            mesh = _volume_sized(robot.links[link], primitive, mesh, context)
        if mesh is None:
            logger.info("link %r has no geometry: not rendered", link)
        else:
            link_meshes[link] = mesh
    if not link_meshes:
        raise ConfigError(
            f"nothing to render below root {root!r} in {path.name}: the selected links "
            f"({', '.join(selected)}) have no geometry or are excluded"
        )

    needed = [root] + ([tip] if tip is not None else []) + list(link_meshes)
    joint_names = robot.joints_on_paths(root, needed)
    frames = [link for link in selected if link == root or _reachable(robot, root, link, joint_names)]
    kinematics = _kinematic_tree(robot, frames, joint_names)
    link_names = [link for link in frames if link in link_meshes]

    verts, faces, owner, count = [], [], [], 0
    for i, link in enumerate(link_names):
        v, f = link_meshes[link]
        verts.append(v)
        faces.append(f + count)
        owner.append(np.full(len(v), i, dtype=np.int64))
        count += len(v)
    lower = [robot.joints[j].lower for j in joint_names]
    upper = [robot.joints[j].upper for j in joint_names]
    return ManipulatorModel(
        name=robot.name,
        urdf_path=str(path),
        root=root,
        tip=tip,
        primitive=primitive,
        link_names=tuple(link_names),
        joint_names=tuple(joint_names),
        joint_lower=torch.tensor(lower, dtype=torch.float64),
        joint_upper=torch.tensor(upper, dtype=torch.float64),
        urdf_joint_names=tuple(robot.joints),
        kinematics=kinematics,
        link_frame_index=torch.tensor([frames.index(link) for link in link_names], dtype=torch.int64),
        verts_link=torch.from_numpy(np.concatenate(verts)).to(torch.float64),
        faces=torch.from_numpy(np.concatenate(faces)).to(torch.int64),
        vert_link_index=torch.from_numpy(np.concatenate(owner)),
    )


def resolve_mesh_path(
    filename: str, urdf_dir: str | Path, package_map: Mapping[str, str | Path] | None = None
) -> Path:
    """The file a URDF mesh name refers to.

    ``package://PKG/rest`` -> ``package_map[PKG]/rest`` if ``PKG`` is mapped, else ``ANCESTOR/rest`` for the
    nearest folder named ``PKG`` among the URDF folder and its parents (the usual ``PKG/urdf/robot.urdf`` layout);
    ``file://`` names and absolute paths are used as they are; other names are relative to the URDF folder.

    Raises:
        AssetError: the file does not exist (the message names it and how it was resolved).
    """
    urdf_dir = Path(urdf_dir)
    if filename.startswith("package://"):
        package, _, rest = filename[len("package://") :].partition("/")
        if package_map and package in package_map:
            candidate = Path(package_map[package]) / rest
        else:
            folder = next((d for d in [urdf_dir.resolve(), *urdf_dir.resolve().parents] if d.name == package), None)
            if folder is None:
                raise AssetError(
                    f"mesh {filename!r}: package {package!r} is not in package_map and no folder named "
                    f"{package!r} contains {urdf_dir}; pass package_map={{{package!r}: FOLDER}}"
                )
            candidate = folder / rest
    elif filename.startswith("file://"):
        candidate = Path(filename[len("file://") :])
    else:
        candidate = urdf_dir / filename
    if not candidate.is_file():
        raise AssetError(f"mesh {filename!r}: file {candidate} not found")
    return candidate


# ---------------------------------------------------------------------------------------------------------------
# URDF parsing


@dataclass(frozen=True)
class _Geometry:
    kind: str  # "box", "cylinder", "sphere" or "mesh"
    size: tuple[float, ...]  # box: (x, y, z); cylinder: (radius, length); sphere: (radius,); mesh: scale (x, y, z)
    filename: str | None  # mesh only
    T_link_geom: np.ndarray  # (4, 4) the element's origin in its link frame


@dataclass(frozen=True)
class _Link:
    name: str
    visuals: tuple[_Geometry, ...]
    collisions: tuple[_Geometry, ...]


@dataclass(frozen=True)
class _Joint:
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
class _Robot:
    name: str
    links: dict[str, _Link]  # in document order
    joints: dict[str, _Joint]  # in document order
    parent_joint: dict[str, _Joint]  # child link -> the joint above it
    children: dict[str, list[_Joint]]  # parent link -> joints below it, in document order

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

    def master(self, joint: _Joint) -> tuple[_Joint, float, float]:
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
            if joint.kind not in _JOINT_TYPES:
                raise ConfigError(
                    f"joint {joint.name!r} is of type {joint.kind!r}; supported on the way to rendered links: "
                    f"{', '.join(_JOINT_TYPES)}"
                )
            master = self.master(joint)[0].name
            if master not in names:
                names.append(master)
        return names


def _reachable(robot: _Robot, root: str, link: str, joint_names: Sequence[str]) -> bool:
    """Whether FK reaches ``link`` from ``root`` with readings of ``joint_names`` only."""
    for child in robot.path(root, link)[1:]:
        joint = robot.parent_joint[child]
        if joint.kind != "fixed" and (joint.kind not in _JOINT_TYPES or robot.master(joint)[0].name not in joint_names):
            return False
    return True


def _kinematic_tree(robot: _Robot, frames: list[str], joint_names: list[str]) -> KinematicTree:
    parent_index, T_parent_frame, joint_type, axis, joint_index, joint_scale, joint_offset = [], [], [], [], [], [], []
    for k, link in enumerate(frames):
        joint = robot.parent_joint[link] if k > 0 else None
        parent_index.append(frames.index(joint.parent) if joint else -1)
        T_parent_frame.append(joint.T_parent_child if joint else np.eye(4))
        if joint is None or joint.kind == "fixed":
            row = (_FIXED, np.zeros(3), -1, 0.0, 0.0)
        else:
            master, scale, offset = robot.master(joint)
            row = (_JOINT_TYPES[joint.kind], joint.axis, joint_names.index(master.name), scale, offset)
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


def _parse_urdf(path: Path) -> _Robot:
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

    links: dict[str, _Link] = {}
    for el in root.findall("link"):
        name = _attr(el, "name", where)
        if name in links:
            raise ConfigError(f"{where}: link {name!r} is defined twice")
        visuals = tuple(g for g in (_geometry(v, f"{where}, link {name!r}") for v in el.findall("visual")) if g)
        collisions = tuple(g for g in (_geometry(c, f"{where}, link {name!r}") for c in el.findall("collision")) if g)
        links[name] = _Link(name, visuals, collisions)
    if not links:
        raise ConfigError(f"{where}: no <link> elements")

    joints: dict[str, _Joint] = {}
    parent_joint: dict[str, _Joint] = {}
    children: dict[str, list[_Joint]] = {name: [] for name in links}
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
    robot = _Robot(root.get("name", path.stem), links, joints, parent_joint, children)
    if len(robot.subtree(tops[0])) != len(links):
        raise ConfigError(f"{where}: some links are not connected to the root link {tops[0]!r}")
    return robot


def _joint(el: ET.Element, where: str) -> _Joint:
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
    return _Joint(name, kind, parent, child, _origin(el, where), axis, lower, upper, mimic)


def _geometry(el: ET.Element, where: str) -> _Geometry | None:
    geometry = el.find("geometry")
    if geometry is None or len(geometry) == 0:
        return None
    shape = geometry[0]
    T = _origin(el, where)
    if shape.tag == "box":
        return _Geometry("box", _floats(_attr(shape, "size", where), 3, where, "box size"), None, T)
    if shape.tag == "cylinder":
        radius = _floats(_attr(shape, "radius", where), 1, where, "cylinder radius")[0]
        length = _floats(_attr(shape, "length", where), 1, where, "cylinder length")[0]
        return _Geometry("cylinder", (radius, length), None, T)
    if shape.tag == "sphere":
        return _Geometry("sphere", _floats(_attr(shape, "radius", where), 1, where, "sphere radius"), None, T)
    if shape.tag == "mesh":
        scale = _floats(shape.get("scale", "1 1 1"), (1, 3), where, "mesh scale")
        return _Geometry("mesh", scale * 3 if len(scale) == 1 else scale, _attr(shape, "filename", where), T)
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


# ---------------------------------------------------------------------------------------------------------------
# Link meshes


@dataclass(frozen=True)
class _MeshContext:
    urdf_dir: Path
    package_map: dict[str, str | Path]
    cache: dict[Path, tuple[np.ndarray, np.ndarray]]  # meshes read during one load_urdf_robot call


def _link_mesh(link: _Link, primitive: str, context: _MeshContext) -> tuple[np.ndarray, np.ndarray] | None:
    """The link's mesh in its link frame, ``(verts (V, 3), faces (F, 3))``, or ``None`` if it has no geometry."""
    elements = _geometry_elements(link, primitive)
    if primitive != "cad" and elements and not link.collisions:
        logger.info("link %r has no collision geometry: using its visual geometry", link.name)
    if not elements:
        return None
    if primitive == "cylinder" and len(elements) == 1 and elements[0].kind == "cylinder":
        return _transformed(_primitive_mesh(elements[0]), elements[0].T_link_geom)  # already one cylinder
    if primitive in ("box", "cylinder"):
        T_link_box, extent = _bounding_box(link.name, elements, context)
        if primitive == "box":
            return _transformed(box_mesh(extent), T_link_box)
        axis = 2 if np.isclose(extent[2], extent.max()) else int(np.argmax(extent))  # ties keep z
        radius = float(np.delete(extent, axis).max()) / 2.0
        T_box_cyl = np.eye(4)
        T_box_cyl[:3, :3] = _Z_TO_AXIS[axis]
        return _transformed(cylinder_mesh(radius, float(extent[axis])), T_link_box @ T_box_cyl)
    meshes = []
    for element in elements:
        if element.kind != "mesh":
            meshes.append(_transformed(_primitive_mesh(element), element.T_link_geom))
        elif primitive == "cad":
            meshes.append(_transformed(_read_mesh(element, context), element.T_link_geom))
        else:
            logger.info("link %r: collision mesh %s replaced by its bounding box", link.name, element.filename)
            T_geom_box, extent = _element_box(element, context)
            meshes.append(_transformed(box_mesh(extent), element.T_link_geom @ T_geom_box))
    return _concatenate(meshes)


def _geometry_elements(link: _Link, primitive: str) -> list[_Geometry]:
    """The elements a link's mesh is built from: its collision ones (its visual ones for ``"cad"``), else the
    others."""
    if primitive == "cad":
        return list(link.visuals or link.collisions)
    return list(link.collisions or link.visuals)


def _volume_sized(link: _Link, primitive: str, mesh: tuple[np.ndarray, np.ndarray], context: _MeshContext
                  ) -> tuple[np.ndarray, np.ndarray]:
    """The link's one-primitive ``mesh`` scaled about its bounding-box centre to the volume of the link's geometry
    (summed over its elements, as closed meshes: primitives meshed, mesh files read); unchanged, with a warning,
    where an element's mesh is not closed."""
    import trimesh

    volume = 0.0
    for element in _geometry_elements(link, primitive):
        verts, faces = _read_mesh(element, context) if element.kind == "mesh" else _primitive_mesh(element)
        part = trimesh.Trimesh(verts, faces, process=True)
        if not part.is_watertight:
            logger.warning("link %r: %s is not a closed mesh, so its volume is unknown: the primitive keeps its "
                           "bounding size", link.name, element.filename or element.kind)  # fmt: skip
            return mesh
        volume += abs(float(part.volume))
    verts, faces = mesh
    own = abs(float(trimesh.Trimesh(verts, faces, process=False).volume))
    scale = (volume / own) ** (1.0 / 3.0)
    centre = (verts.min(axis=0) + verts.max(axis=0)) / 2.0
    logger.debug("link %r: primitive scaled by %.3f to the geometry's volume %.3g m^3", link.name, scale, volume)
    return centre + (verts - centre) * scale, faces


# rotations taking the cylinder's z axis to x, y or z
_Z_TO_AXIS = (
    np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]]),
    np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]]),
    np.eye(3),
)


def _bounding_box(name: str, elements: Sequence[_Geometry], context: _MeshContext) -> tuple[np.ndarray, np.ndarray]:
    """``(T_link_box (4, 4), extent (3,))``: a box around the elements, centred at ``T_link_box``'s origin."""
    if len(elements) == 1:
        T_geom_box, extent = _element_box(elements[0], context)
        return elements[0].T_link_geom @ T_geom_box, extent
    corners = []
    for element in elements:
        T_geom_box, extent = _element_box(element, context)
        signs = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64)
        corners.append(_transform_points(element.T_link_geom @ T_geom_box, signs * extent / 2))  # (8, 3)
    points = np.concatenate(corners)
    lo, hi = points.min(axis=0), points.max(axis=0)
    T_link_box = np.eye(4)
    T_link_box[:3, 3] = (lo + hi) / 2
    logger.debug("link %r: %d elements bounded by one box in the link frame", name, len(elements))
    return T_link_box, hi - lo


def _element_box(element: _Geometry, context: _MeshContext) -> tuple[np.ndarray, np.ndarray]:
    """``(T_geom_box (4, 4), extent (3,))``: the element's bounding box in its own frame."""
    T = np.eye(4)
    if element.kind == "box":
        return T, np.array(element.size)
    if element.kind == "cylinder":
        radius, length = element.size
        return T, np.array([2 * radius, 2 * radius, length])
    if element.kind == "sphere":
        return T, np.full(3, 2 * element.size[0])
    verts, _ = _read_mesh(element, context)
    lo, hi = verts.min(axis=0), verts.max(axis=0)
    T[:3, 3] = (lo + hi) / 2
    extent = hi - lo
    if not (extent > 0).all():
        raise AssetError(f"mesh {element.filename!r}: flat or empty (bounding box {extent.tolist()} m)")
    return T, extent


def _primitive_mesh(element: _Geometry) -> tuple[np.ndarray, np.ndarray]:
    if element.kind == "box":
        return box_mesh(element.size)
    if element.kind == "cylinder":
        return cylinder_mesh(*element.size)
    return sphere_mesh(element.size[0])


def _read_mesh(element: _Geometry, context: _MeshContext) -> tuple[np.ndarray, np.ndarray]:
    """The mesh file's vertices (scaled as the URDF says, in the element's frame) and faces."""
    import trimesh  # only needed for mesh files

    path = resolve_mesh_path(element.filename or "", context.urdf_dir, context.package_map)
    if path not in context.cache:
        try:
            mesh = trimesh.load(str(path), force="mesh")
        except Exception as err:  # trimesh raises many types (ValueError, KeyError, ImportError for .dae, ...)
            raise AssetError(f"mesh {element.filename!r}: cannot read {path} ({type(err).__name__}: {err})") from None
        if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
            raise AssetError(f"mesh {element.filename!r}: cannot read {path} (no triangles in it)")
        context.cache[path] = (np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64))
    verts, faces = context.cache[path]
    scale = np.asarray(element.size)
    if np.prod(scale) < 0:  # a mirroring scale would turn the faces inside out
        faces = faces[:, ::-1]
    return verts * scale, faces


def _transformed(mesh: tuple[np.ndarray, np.ndarray], T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    verts, faces = mesh
    return _transform_points(T, verts), faces


def _transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    return points @ T[:3, :3].T + T[:3, 3]  # (N, 3)


def _concatenate(meshes: Sequence[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    offsets = np.cumsum([0] + [len(v) for v, _ in meshes[:-1]])
    verts = np.concatenate([v for v, _ in meshes])
    faces = np.concatenate([f + o for (_, f), o in zip(meshes, offsets)])
    return verts, faces


def _skew(axis: torch.Tensor) -> torch.Tensor:
    """``(K, 3)`` vectors to ``(K, 3, 3)`` cross-product matrices."""
    x, y, z = axis.unbind(-1)
    zero = torch.zeros_like(x)
    return torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], dim=-1).reshape(*axis.shape[:-1], 3, 3)
