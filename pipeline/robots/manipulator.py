"""Rigid manipulators as rendered: the rendered links' meshes and FK from joint readings to the root frame.

Which links are rendered (DESIGN.md 4): the subtree below ``root`` (with ``tip``: the chain from ``root`` down to
``tip`` plus the subtree below ``tip``), minus the links named in ``exclude`` (only those links, not their
children), minus links without geometry. Only the movable joints on the way from ``root`` to a rendered link (or
to ``tip``) need a reading; they are ``ManipulatorModel.joint_names``.

The description is parsed by :mod:`pipeline.robots.description`, link meshes come from
:mod:`pipeline.robots.link_geometry`, mesh files from :mod:`pipeline.robots.mesh_io`.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from tqdm.auto import tqdm

from pipeline.checks import check_choice, check_shape
from pipeline.errors import ConfigError, ShapeError
from pipeline.robots.description import Kinematics, kinematics_for, read_description
from pipeline.robots.link_geometry import (PRIMITIVE_CHOICES, PRIMITIVE_SIZE_CHOICES, link_mesh, resolved_primitive,
                                           volume_sized)
from pipeline.robots.mesh_io import MeshContext, default_mesh_cache

__all__ = ["ManipulatorModel", "load_robot", "load_urdf_robot"]

logger = logging.getLogger(__name__)

#: the default of :func:`load_robot`'s ``cad_tolerance_m`` (metres; ``None``: no tolerance)
CAD_TOLERANCE_M: float | None = None
#: a ``"cad"`` model's ``outline``: its links' meshes within this distance (metres) of their full meshes' silhouettes
#: (:func:`pipeline.robots.mesh_io.simplify_within`), which the pose fit polishes its answer with
CAD_OUTLINE_TOLERANCE_M = 1e-3
#: :func:`load_robot`'s progress bar appears once building the meshes has taken this long (seconds)
LOAD_PROGRESS_DELAY_S = 1.0


@dataclass(frozen=True, kw_only=True, eq=False)
class ManipulatorModel:
    """A rigid manipulator as rendered: link meshes in their link frames, and FK from joint values to the root.

    Build it with :func:`load_robot`. Plain strings, tuples, tensors and the description's float64
    pytorch-kinematics chain (picklable, no open files).

    Fields:
        name: the URDF's robot name.
        description_path: the description file (URDF, MJCF or SDF) it was loaded from.
        format: the description's format, ``"urdf"``, ``"mjcf"`` or ``"sdf"``.
        root: the link whose frame every pose is expressed in.
        tip: the tip link that cut the rendered chain, or ``None`` for the whole subtree below ``root``.
        primitive: how link geometry was built, one of ``PRIMITIVE_CHOICES``.
        link_names: the ``L`` rendered links, parents before children.
        joint_names: the ``J`` joints that need a reading, in the order of the joint vector.
        joint_lower, joint_upper: ``(J,)`` float64 limits (rad or m; +-inf where the URDF gives none).
        description_joint_names: every joint of the description (readings for joints not needed are ignored).
        kinematics: FK (the description's pytorch-kinematics chain) of the frames below ``root``: the rendered
            links, ``tip``, and geometry-less links that need no further readings (e.g. a camera mount); frame 0 is
            ``root``.
        link_frame_index: ``(L,)`` int64, frame index in ``kinematics`` of each rendered link.
        verts_link: ``(V, 3)`` float64 vertices, metres, each in its own link's frame.
        faces: ``(F, 3)`` int64 triangles indexing ``verts_link``, counter-clockwise seen from outside.
        vert_link_index: ``(V,)`` int64, the rendered link (index into ``link_names``) of each vertex;
            non-decreasing (each link's vertices are one block).
        outline: the same robot drawn with its visual meshes (``primitive`` ``"cad"``, the same links, joints and
            kinematics), kept beside a geometry that is wider than the links (``"auto"`` links drawn as hulls,
            ``"hull"``): the pose fit asks it whether a fit's pose explains the mask (``PoseFitConfig.
            retry_outline_loss``) and may polish its answer with it (``PoseFitConfig.outline_polish``); beside
            ``"cad"`` meshes decimated to an area's budget, the same meshes within ``CAD_OUTLINE_TOLERANCE_M`` of
            their outline, which the fit's answer is polished with; ``None`` where there is none (see
            :func:`load_robot`'s ``outline``).
    """

    name: str
    description_path: str
    format: str
    root: str
    tip: str | None
    primitive: str
    link_names: tuple[str, ...]
    joint_names: tuple[str, ...]
    joint_lower: torch.Tensor
    joint_upper: torch.Tensor
    description_joint_names: tuple[str, ...]
    kinematics: Kinematics
    link_frame_index: torch.Tensor
    verts_link: torch.Tensor
    faces: torch.Tensor
    vert_link_index: torch.Tensor
    outline: ManipulatorModel | None = None

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
        if self.kinematics.joint_matrix.shape[1] != J:
            raise ConfigError(f"kinematics: expected a joint map for the {J} joints {self.joint_names}")
        if self.outline is not None and (self.outline.primitive != "cad" or self.outline.outline is not None
                                         or self.outline.link_names != self.link_names
                                         or self.outline.joint_names != self.joint_names):
            raise ConfigError("outline: expected the same links and joints drawn as \"cad\", without an outline of "
                              "its own")

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

        Names of the description's joints the model does not need (fixed, mimic, outside the rendered links) are ignored.

        Args:
            joint_values: joint name -> value, radians (revolute) or metres (prismatic).
            zero_missing: set joints without a reading to 0 (with a logged warning) instead of raising.

        Returns:
            ``(J,)`` float64 in the order of ``joint_names``.

        Raises:
            ConfigError: a name that is no joint of the URDF, a missing reading (unless ``zero_missing``), or a
                value that is not a finite number; the message lists the expected or the missing names.
        """
        unknown = [n for n in joint_values if n not in self.description_joint_names]
        if unknown:
            raise ConfigError(
                f"unknown joint name(s) {', '.join(map(repr, unknown))} for {Path(self.description_path).name}; "
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



def load_robot(
    path: str | Path,
    root: str | None = None,
    *,
    tip: str | None = None,
    exclude: Sequence[str] = (),
    primitive: str = "auto",
    primitive_size: str = "bbox",
    package_map: Mapping[str, str | Path] | None = None,
    cad_faces: int = 3000,
    cad_faces_per_cm2: float | None = 1.0,
    cad_tolerance_m: float | None = CAD_TOLERANCE_M,
    hull_faces: int = 300,
    mesh_cache: str | Path | None = "default",
    outline: bool | None = None,
    progress: bool = False,
) -> ManipulatorModel:
    """Load a robot description (URDF, MJCF or SDF; see :mod:`pipeline.robots.description`) and build the rendered
    links' meshes and their FK (see the module docstring for the rules).

    Args:
        path: the ``.urdf``, MJCF ``.xml`` / ``.mjcf`` or ``.sdf`` file (plain URDF: run xacro first).
        root: link (MJCF: body) whose frame poses are expressed in (often the base link), or ``None`` meaning
            *the description's top link* (the one no joint has as its child; MJCF: ``world``).
        tip: if given, render only the chain from ``root`` to ``tip`` plus the subtree below ``tip``; it must be
            ``root`` or below it.
        exclude: links not to render (only these links; their children stay).
        primitive: one of ``PRIMITIVE_CHOICES`` (:mod:`pipeline.robots.link_geometry`).
        primitive_size: ``"box"`` / ``"cylinder"`` sizing: ``"bbox"`` (bounding, the default) or ``"volume"``
            (scaled to the volume of the link's geometry).
        package_map: package name -> folder, for ``package://`` mesh names (see
            :func:`pipeline.robots.mesh_io.resolve_mesh_path`).
        cad_faces: ``"cad"``: each link's mesh decimated to at most this many faces (>= 4).
        cad_faces_per_cm2: ``"cad"``: and to this many faces per cm^2 of the link's surface (> 0; at least
            ``link_geometry.CAD_MIN_FACES``); ``None``: ``cad_faces`` for every link. The default, 1, gives
            Panda's arm 9 300 faces, UR5's 19 400 and Baxter's left arm 20 100 (against 28 200, 24 500 and
            34 500 at 3000 per link) at PCK rates within one view of those, medians about a millimetre higher
            (docs/any-manipulator.md).
        cad_tolerance_m: ``"cad"``: a link's budget above is doubled until its silhouettes stray at most this far
            (metres) from those of its full mesh, seen from 13 directions
            (:func:`pipeline.robots.mesh_io.simplify_within`); ``None``: the budget alone. By area alone UR5's,
            Panda's and Baxter's end links were drawn 4-7 mm off their outline (docs/any-manipulator.md).
        hull_faces: ``"hull"``: each link's convex hull decimated to at most this many faces (>= 4).
        mesh_cache: folder where simplified meshes are cached; ``"default"`` for
            :func:`pipeline.robots.mesh_io.default_mesh_cache`, ``None`` for no disk cache.
        outline: also build :attr:`ManipulatorModel.outline`, the links' ``"cad"`` meshes: beside hulls with
            ``cad_faces`` and ``cad_faces_per_cm2`` (``cad_tolerance_m`` does not apply: the polishes that draw
            them were not re-timed with finer meshes), beside ``"cad"`` meshes those meshes within
            ``CAD_OUTLINE_TOLERANCE_M`` (none where every link is within it already, e.g. ``cad_tolerance_m`` at
            most that). ``None`` (the default): where ``primitive`` draws some link as the hull of its visual
            meshes (``"auto"`` with a visual mesh, ``"hull"``), so that the pose fit can tell a hull's overdraw
            from a pose that does not explain the mask, and for ``"cad"``, whose fits end with a polish drawn
            within 1 mm: on Panda, UR5 and Baxter the area's budget leaves links 4-7 mm off their outline
            (docs/any-manipulator.md). The first load of a robot's 1 mm meshes takes a while (UR5: about a
            minute and a half, one thread beside another run); they are cached on disk (``mesh_cache``).
        progress: show a tqdm progress bar over the links' meshes (and the outline's) where building them takes
            more than ``LOAD_PROGRESS_DELAY_S`` (a first load that decimates meshes; a cached load shows none).

    Raises:
        AssetError: the description or a mesh file it needs is missing or unreadable.
        ConfigError: a malformed description, unknown link names (the message lists the valid ones), ``tip`` not
            below ``root``, nothing to render, or an unsupported joint type on the way to a rendered link.
    """
    path = Path(path)
    check_choice(primitive, PRIMITIVE_CHOICES, "primitive")
    check_choice(primitive_size, PRIMITIVE_SIZE_CHOICES, "primitive_size")
    if isinstance(exclude, str):
        raise ConfigError(f"exclude: expected a sequence of link names, got the string {exclude!r}")
    for name, value in (("cad_faces", cad_faces), ("hull_faces", hull_faces)):
        if isinstance(value, bool) or not isinstance(value, int) or value < 4:
            raise ConfigError(f"{name}: expected an integer >= 4, got {value!r}")
    if outline is not None and not isinstance(outline, bool):
        raise ConfigError(f"outline: expected True, False or None (where links are drawn as hulls), got {outline!r}")
    if cad_faces_per_cm2 is not None and (
        isinstance(cad_faces_per_cm2, bool) or not isinstance(cad_faces_per_cm2, (int, float))
        or not math.isfinite(cad_faces_per_cm2) or cad_faces_per_cm2 <= 0
    ):
        raise ConfigError(f"cad_faces_per_cm2: expected a number > 0 or None, got {cad_faces_per_cm2!r}")
    if cad_tolerance_m is not None and (
        isinstance(cad_tolerance_m, bool) or not isinstance(cad_tolerance_m, (int, float))
        or not math.isfinite(cad_tolerance_m) or cad_tolerance_m <= 0
    ):
        raise ConfigError(f"cad_tolerance_m: expected a length > 0 (metres) or None, got {cad_tolerance_m!r}")
    disk_cache = default_mesh_cache() if mesh_cache == "default" else None if mesh_cache is None else Path(mesh_cache)
    robot = read_description(path)
    if root is None:
        root = next(link for link in robot.links if link not in robot.parent_joint)
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

    context = MeshContext(urdf_dir=path.parent, package_map=dict(package_map or {}), cache={}, disk_cache=disk_cache)
    link_meshes: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for link in _progress([link for link in selected if link not in exclude], "link meshes", progress):
        mesh = link_mesh(robot.links[link], primitive, context, cad_faces=cad_faces,
                         cad_faces_per_cm2=cad_faces_per_cm2, cad_tolerance_m=cad_tolerance_m,
                         hull_faces=hull_faces)  # fmt: skip
        if mesh is not None and primitive in ("box", "cylinder") and primitive_size == "volume":
            mesh = volume_sized(robot.links[link], primitive, mesh, context)
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
    frames = [link for link in selected if link == root or robot.reachable(root, link, joint_names)]
    link_names = [link for link in frames if link in link_meshes]

    lower = [robot.joints[j].lower for j in joint_names]
    upper = [robot.joints[j].upper for j in joint_names]
    model = ManipulatorModel(
        name=robot.name,
        description_path=str(path),
        format=robot.format,
        root=root,
        tip=tip,
        primitive=primitive,
        link_names=tuple(link_names),
        joint_names=tuple(joint_names),
        joint_lower=torch.tensor(lower, dtype=torch.float64),
        joint_upper=torch.tensor(upper, dtype=torch.float64),
        description_joint_names=tuple(robot.joints),
        kinematics=kinematics_for(robot, frames, joint_names),
        link_frame_index=torch.tensor([frames.index(link) for link in link_names], dtype=torch.int64),
        **_link_blocks([link_meshes[link] for link in link_names]),
    )
    if outline is None:
        outline = primitive in ("hull", "cad") or (primitive == "auto" and any(
            resolved_primitive(robot.links[link], primitive) == "hull" for link in link_names))
    if not outline:
        return model
    if primitive == "cad":  # the same meshes within the outline's tolerance, where some link is not yet
        if cad_tolerance_m is not None and cad_tolerance_m <= CAD_OUTLINE_TOLERANCE_M:
            return model
        drawn = [link_mesh(robot.links[link], "cad", context, cad_faces=cad_faces,
                           cad_faces_per_cm2=cad_faces_per_cm2, cad_tolerance_m=CAD_OUTLINE_TOLERANCE_M)
                 for link in _progress(link_names, "outline meshes (1 mm)", progress)]  # fmt: skip
        if all(len(mesh[1]) == len(link_meshes[link][1]) for mesh, link in zip(drawn, link_names)):
            return model
    else:  # the area's budget alone (the outline's polishes beside hulls were not re-timed with finer meshes)
        drawn = [link_mesh(robot.links[link], "cad", context, cad_faces=cad_faces,
                           cad_faces_per_cm2=cad_faces_per_cm2)
                 for link in _progress(link_names, "outline meshes", progress)]  # fmt: skip
    if any(mesh is None for mesh in drawn):
        return model
    return dataclasses.replace(model, outline=dataclasses.replace(model, primitive="cad", **_link_blocks(drawn)))


def _progress(links: Sequence[str], what: str, show: bool) -> Sequence[str]:
    """``links``, iterated under a tqdm bar named ``what`` when ``show`` (it appears only after
    ``LOAD_PROGRESS_DELAY_S``, and not where stderr is not a terminal)."""
    if not show:
        return links
    return tqdm(links, desc=what, unit="link", delay=LOAD_PROGRESS_DELAY_S, leave=False, disable=None)


def _link_blocks(meshes: Sequence[tuple[np.ndarray, np.ndarray]]) -> dict[str, torch.Tensor]:
    """``verts_link``, ``faces`` and ``vert_link_index`` of :class:`ManipulatorModel` from each rendered link's
    ``(verts (V_l, 3), faces (F_l, 3))``, in link order."""
    verts, faces, owner, count = [], [], [], 0
    for i, (v, f) in enumerate(meshes):
        verts.append(v)
        faces.append(f + count)
        owner.append(np.full(len(v), i, dtype=np.int64))
        count += len(v)
    return {"verts_link": torch.from_numpy(np.concatenate(verts)).to(torch.float64),
            "faces": torch.from_numpy(np.concatenate(faces)).to(torch.int64),
            "vert_link_index": torch.from_numpy(np.concatenate(owner))}


def load_urdf_robot(urdf_path: str | Path, root: str | None = None, **options) -> ManipulatorModel:
    """:func:`load_robot` under its earlier name (any description format works)."""
    return load_robot(urdf_path, root, **options)
