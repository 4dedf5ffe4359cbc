"""Mesh files of robot descriptions: resolving their names and reading them (trimesh).

Convention: vertices in metres in the geometry element's own frame, scaled as the description says; faces
``(F, 3)`` int64, counter-clockwise seen from outside. COLLADA ``.dae`` files need the optional ``pycollada``
package. See ``docs/`` (robot descriptions) for how names are resolved.
"""

from __future__ import annotations

import hashlib
import logging
import os
import xml.etree.ElementTree as ET
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from pipeline.errors import AssetError

if TYPE_CHECKING:
    from pipeline.robots.description import Geometry

__all__ = ["MeshContext", "default_mesh_cache", "read_mesh", "resolve_mesh_path", "simplify_mesh"]

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class MeshContext:
    """What reading a description's meshes needs: where names resolve, the meshes read so far in this load (by
    path), and the on-disk cache folder for simplified meshes (``None``: no disk cache)."""

    urdf_dir: Path
    package_map: dict[str, str | Path]
    cache: dict[Path, tuple[np.ndarray, np.ndarray]]  # meshes read during one load_robot call
    disk_cache: Path | None = None


def default_mesh_cache() -> Path:
    """``$PIPELINE_MESH_CACHE``, else ``$XDG_CACHE_HOME/robot-state-from-image/meshes`` (``~/.cache/...``)."""
    if os.environ.get("PIPELINE_MESH_CACHE"):
        return Path(os.environ["PIPELINE_MESH_CACHE"])
    base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return base / "robot-state-from-image" / "meshes"


# fast-simplification's aggressiveness (0-10). Its default (7) moved UR5's visual meshes up to 14 mm outside their
# bounds and cut notches into their ends at 3000 faces (docs/any-manipulator.md); 3 keeps them within 1 mm at about
# the same face count.
DECIMATION_AGGRESSION = 3


def simplify_mesh(
    verts: np.ndarray, faces: np.ndarray, face_budget: int, disk_cache: Path | None
) -> tuple[np.ndarray, np.ndarray]:
    """The mesh decimated to ``face_budget`` faces by quadric decimation (``fast-simplification`` through
    ``trimesh.Trimesh.simplify_quadric_decimation``, aggressiveness ``DECIMATION_AGGRESSION``); unchanged if it has
    no more faces than that. A mesh the decimation cannot collapse that far without moving its surface keeps more
    (UR5's upper arm: 7924 faces for a budget of 3000).

    The result is cached in ``disk_cache`` (if given) under the SHA-256 of the mesh's arrays, the budget and
    ``DECIMATION_AGGRESSION``, so a robot's meshes are simplified once per machine.

    Args:
        verts: ``(V, 3)`` float64, metres.
        faces: ``(F, 3)`` int64.
        face_budget: faces wanted, >= 4.
        disk_cache: folder for ``<key>.npz`` files, or ``None``.
    """
    if len(faces) <= face_budget:
        return verts, faces
    verts = np.ascontiguousarray(verts, dtype=np.float64)
    faces = np.ascontiguousarray(faces, dtype=np.int64)
    recipe = f"{face_budget}:aggression={DECIMATION_AGGRESSION}".encode()
    key = hashlib.sha256(verts.tobytes() + faces.tobytes() + recipe).hexdigest()[:32]
    cached = disk_cache / f"{key}.npz" if disk_cache is not None else None
    if cached is not None and cached.is_file():
        with np.load(cached) as data:
            return data["verts"], data["faces"]
    import trimesh

    mesh = trimesh.Trimesh(verts, faces, process=True)  # merges duplicate vertices so decimation sees edges
    simple = mesh.simplify_quadric_decimation(face_count=face_budget, aggression=DECIMATION_AGGRESSION)
    out = np.asarray(simple.vertices, dtype=np.float64), np.asarray(simple.faces, dtype=np.int64)
    logger.debug("mesh simplified from %d to %d faces", len(faces), len(out[1]))
    if cached is not None:
        try:
            cached.parent.mkdir(parents=True, exist_ok=True)
            partial = cached.with_suffix(f".{os.getpid()}.tmp.npz")
            np.savez(partial, verts=out[0], faces=out[1])
            partial.replace(cached)  # atomic: parallel workers never read half a file
        except OSError as err:
            logger.warning("mesh cache %s not writable (%s): simplified meshes are not kept", disk_cache, err)
    return out



def resolve_mesh_path(
    filename: str, urdf_dir: str | Path, package_map: Mapping[str, str | Path] | None = None
) -> Path:
    """The file a URDF mesh name refers to.

    ``package://PKG/rest`` -> ``package_map[PKG]/rest`` if ``PKG`` is mapped, else ``ANCESTOR/rest`` for the
    nearest folder named ``PKG`` among the URDF folder and its parents (the usual ``PKG/urdf/robot.urdf`` layout);
    SDF's ``model://MODEL/rest`` the same way (Gazebo looks ``MODEL`` up in its model path); ``package:///PKG/rest``
    (an empty package name, as Talos' full URDFs write) as ``package://PKG/rest``; ``file://`` names and absolute
    paths are used as they are; other names are relative to the URDF folder.

    Raises:
        AssetError: the file does not exist (the message names it and how it was resolved).
    """
    urdf_dir = Path(urdf_dir)
    scheme = next((s for s in ("package://", "model://") if filename.startswith(s)), None)
    if scheme is not None:
        package, _, rest = filename[len(scheme) :].lstrip("/").partition("/")
        if not package:
            raise AssetError(f"mesh {filename!r}: names no package (expected {scheme}PACKAGE/path)")
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


def _collada_without_materials(path: Path):
    """A COLLADA file read by trimesh with its materials left out: pycollada (through trimesh 4-5) drops a scene
    node whose material it cannot resolve, e.g. a texture's missing ``<surface>`` (ANYmal B's feet), so the file
    reads as empty; the geometry and the nodes' transforms (unit scale included) do not depend on them."""
    import io

    import trimesh

    root = ET.parse(path).getroot()
    namespace = root.tag[: root.tag.index("}") + 1] if root.tag.startswith("{") else ""
    unread = {namespace + tag for tag in ("bind_material", "library_materials", "library_effects", "library_images")}
    for parent in root.iter():
        for child in list(parent):
            if child.tag in unread:
                parent.remove(child)
    return trimesh.load(io.BytesIO(ET.tostring(root)), file_type="dae", force="mesh")


def read_mesh(element: Geometry, context: MeshContext) -> tuple[np.ndarray, np.ndarray]:
    """The mesh's vertices (scaled as the description says, in the element's frame) and faces: the element's own
    arrays where it carries them (MJCF), else its file read by trimesh."""
    import trimesh  # only needed for mesh files

    if element.verts is not None and element.faces is not None:
        return element.verts * np.asarray(element.size), element.faces
    path = resolve_mesh_path(element.filename or "", context.urdf_dir, context.package_map)
    if path not in context.cache:
        try:
            mesh = trimesh.load(str(path), force="mesh")
            if path.suffix.lower() == ".dae" and len(mesh.faces) == 0:
                mesh = _collada_without_materials(path)
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

