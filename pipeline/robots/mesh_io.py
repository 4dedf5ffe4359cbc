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

__all__ = [
    "MeshContext", "default_mesh_cache", "read_mesh", "resolve_mesh_path", "silhouette_deviation", "simplify_mesh",
    "simplify_within",
]

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
    cached = _cache_file(verts, faces, f"{face_budget}:aggression={DECIMATION_AGGRESSION}", disk_cache)
    if cached is not None and cached.is_file():
        return _load(cached)
    import trimesh

    mesh = trimesh.Trimesh(verts, faces, process=True)  # merges duplicate vertices so decimation sees edges
    simple = mesh.simplify_quadric_decimation(face_count=face_budget, aggression=DECIMATION_AGGRESSION)
    out = np.asarray(simple.vertices, dtype=np.float64), np.asarray(simple.faces, dtype=np.int64)
    logger.debug("mesh simplified from %d to %d faces", len(faces), len(out[1]))
    if cached is not None:
        _save(cached, out)
    return out


def _cache_file(verts: np.ndarray, faces: np.ndarray, recipe: str, disk_cache: Path | None) -> Path | None:
    """Where a simplified mesh of ``verts``/``faces`` made by ``recipe`` is cached: ``<SHA-256>.npz`` in
    ``disk_cache``, or ``None`` without a cache."""
    key = hashlib.sha256(verts.tobytes() + faces.tobytes() + recipe.encode()).hexdigest()[:32]
    return disk_cache / f"{key}.npz" if disk_cache is not None else None


def _load(cached: Path) -> tuple[np.ndarray, np.ndarray]:
    with np.load(cached) as data:
        return data["verts"], data["faces"]


def _save(cached: Path, mesh: tuple[np.ndarray, np.ndarray]) -> None:
    try:
        cached.parent.mkdir(parents=True, exist_ok=True)
        partial = cached.with_suffix(f".{os.getpid()}.tmp.npz")
        np.savez(partial, verts=mesh[0], faces=mesh[1])
        partial.replace(cached)  # atomic: parallel workers never read half a file
    except OSError as err:
        logger.warning("mesh cache %s not writable (%s): simplified meshes are not kept", cached.parent, err)


#: view directions of :func:`silhouette_deviation`: one of each opposite pair of the 26 directions to a cube's
#: faces, edges and corners (a view and its opposite draw mirrored silhouettes)
SILHOUETTE_DIRECTIONS = tuple(
    (x, y, z) for x in (-1, 0, 1) for y in (-1, 0, 1) for z in (-1, 0, 1) if (x, y, z) > (0, 0, 0)
)


def silhouette_deviation(
    a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray], pixel_m: float
) -> float:
    """How far (metres) the silhouette of mesh ``b`` strays from that of mesh ``a``: the largest distance from a
    pixel drawn by one of them and not the other to the nearest pixel of the other, over parallel projections along
    the 13 ``SILHOUETTE_DIRECTIONS``, at ``pixel_m`` per pixel (a multiple of about a pixel; two meshes that draw
    the same pixels give 0). Each triangle is drawn by OpenCV's ``fillConvexPoly`` (at 1/16 px; this layer does not
    import the renderer), distances by OpenCV's exact Euclidean distance transform.

    Args:
        a, b: ``(verts (V, 3) metres, faces (F, 3))`` meshes in the same frame.
        pixel_m: pixel size, metres (> 0).
    """
    import cv2

    if not pixel_m > 0:
        raise ValueError(f"pixel_m: expected a size > 0, got {pixel_m!r}")
    both = np.concatenate([a[0], b[0]])
    centre = (both.min(0) + both.max(0)) / 2
    radius = float(np.linalg.norm(both - centre, axis=1).max())
    side = int(np.ceil(2 * radius / pixel_m)) + 4
    worst = 0.0
    for d in SILHOUETTE_DIRECTIONS:
        z = np.asarray(d, dtype=np.float64) / np.linalg.norm(d)
        x = np.cross(z, [1.0, 0.0, 0.0] if abs(z[0]) < 0.9 else [0.0, 1.0, 0.0])
        x /= np.linalg.norm(x)
        axes = np.stack([x, np.cross(z, x)], axis=1)  # (3, 2): the view's image axes in the mesh frame
        drawn = []
        for verts, faces in (a, b):
            uv = np.round(((verts - centre) @ axes / pixel_m + side / 2) * 16).astype(np.int32)
            image = np.zeros((side, side), np.uint8)
            for triangle in uv[faces]:
                cv2.fillConvexPoly(image, triangle, 1, cv2.LINE_8, 4)
            drawn.append(image.astype(bool))
        for mine, other in (drawn, drawn[::-1]):
            stray = mine & ~other
            if stray.any():
                to_other = cv2.distanceTransform((~other).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
                worst = max(worst, float(to_other[stray].max()))
    return worst * pixel_m


#: version of :func:`silhouette_deviation` and of the pixel size :func:`simplify_within` measures at, in the
#: cache key of its choices (change it with either)
_WITHIN_MEASURE = "fillConvexPoly-13-views-half-tolerance"


def simplify_within(
    verts: np.ndarray, faces: np.ndarray, face_budget: int, tolerance_m: float, disk_cache: Path | None
) -> tuple[np.ndarray, np.ndarray]:
    """The mesh decimated (:func:`simplify_mesh`) to ``face_budget`` faces, or to twice, four times, ... that many
    until its silhouettes stray at most ``tolerance_m`` from the mesh's own (:func:`silhouette_deviation`, pixels
    of half the tolerance), or the mesh itself where no budget below its face count does. A face budget by
    area alone left UR5's and Panda's end links 4-5 mm off their outline (``docs/any-manipulator.md``).

    The choice is cached in ``disk_cache`` (if given) under the SHA-256 of the mesh, the budget, the tolerance,
    ``DECIMATION_AGGRESSION`` and the measure's version (``_WITHIN_MEASURE``).
    """
    if len(faces) <= face_budget:
        return verts, faces
    verts = np.ascontiguousarray(verts, dtype=np.float64)
    faces = np.ascontiguousarray(faces, dtype=np.int64)
    recipe = f"within:{face_budget}:{tolerance_m!r}:aggression={DECIMATION_AGGRESSION}:{_WITHIN_MEASURE}"
    cached = _cache_file(verts, faces, recipe, disk_cache)
    if cached is not None and cached.is_file():
        return _load(cached)
    budget = face_budget
    while True:
        out = simplify_mesh(verts, faces, budget, disk_cache)
        if len(out[1]) >= len(faces) or silhouette_deviation((verts, faces), out, tolerance_m / 2) <= tolerance_m:
            break
        budget *= 2
    logger.debug("mesh simplified from %d to %d faces within %g m", len(faces), len(out[1]), tolerance_m)
    if cached is not None:
        _save(cached, out)
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

