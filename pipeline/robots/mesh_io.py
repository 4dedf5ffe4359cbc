"""Mesh files of robot descriptions: resolving their names and reading them (trimesh).

Convention: vertices in metres in the geometry element's own frame, scaled as the description says; faces
``(F, 3)`` int64, counter-clockwise seen from outside. COLLADA ``.dae`` files need the optional ``pycollada``
package. See ``docs/`` (robot descriptions) for how names are resolved.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from pipeline.errors import AssetError

if TYPE_CHECKING:
    from pipeline.robots.description import Geometry

__all__ = ["MeshContext", "read_mesh", "resolve_mesh_path"]


@dataclass(frozen=True)
class MeshContext:
    urdf_dir: Path
    package_map: dict[str, str | Path]
    cache: dict[Path, tuple[np.ndarray, np.ndarray]]  # meshes read during one load_urdf_robot call



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


def read_mesh(element: Geometry, context: MeshContext) -> tuple[np.ndarray, np.ndarray]:
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

