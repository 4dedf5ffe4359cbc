"""Link geometry: each rendered link's triangle mesh in its link frame, built from the description's elements.

Geometry per rendered link, by ``primitive`` (a link's geometry is its collision elements, or its visual elements
where it has no collision element; for ``"cad"`` the other way round):

- ``"auto"`` (the default): ``"hull"`` for a link whose visual geometry includes a mesh, ``"collision"`` for the
  others. Real descriptions' collision geometry is often crude (Baxter's arm: a few 12 cm cylinders), and the
  hull of the visual meshes follows the link; a link drawn from primitives keeps them as they are (a hull would
  merge them into one convex blob). Chosen on the cross-robot benchmark (``docs/any-manipulator.md``).
- ``"collision"``: each box, cylinder, capsule, sphere and ellipsoid as a closed triangle mesh; a mesh element is
  replaced by its convex hull (decimated to ``hull_faces``): most real descriptions carry only mesh collision
  geometry, and its bounding box, used until this release, cost 7-20 cm of depth on real arms
  (``docs/accuracy.md``, cross-robot table).
- ``"box"`` / ``"cylinder"``: one primitive per link, sized by the bounding box of the link's geometry: in the
  element's own frame when the link has one element, else axis-aligned in the link frame. The cylinder's axis
  follows the longest side of that box (its z side on ties), its radius is half the larger of the two other sides.
  A link whose geometry is one box (one cylinder) keeps it as it is in ``"box"`` (``"cylinder"``) mode.
  ``primitive_size="volume"`` then scales the primitive about its centre to the volume of the link's geometry
  (the sum of its elements' volumes, overlaps counted twice; a mesh element that is not closed leaves the link at
  its bounding size, with a warning): a primitive around a link covers more of the image than the link does, and
  the pose fit pays that back in depth (``docs/accuracy.md``, "Without CAD meshes").
- ``"cad"``: the visual meshes (:mod:`pipeline.robots.mesh_io`), scaled as the description says; primitive
  visual elements meshed as in ``"collision"``; each link's mesh decimated (quadric decimation, cached on disk) to
  ``cad_faces_per_cm2`` faces per square centimetre of its surface, at most ``cad_faces`` and at least
  ``CAD_MIN_FACES``, so real robots' CAD (Baxter's arm: ~150 000 faces) renders fast and a small link (a finger)
  gets no more detail per area than a large one (``cad_faces_per_cm2=None``: ``cad_faces`` for every link).
- ``"hull"``: the convex hull of the link's geometry (its visual meshes and primitives where it has visual
  elements, else its collision ones), decimated to ``hull_faces``: a closed, convex stand-in fitted to the link's
  surface for descriptions whose collision geometry is crude, without rendering the CAD itself.

Primitive meshes come from :mod:`pipeline.shapes.primitives` (subdivided, watertight, outward winding). Meshes are
``(verts (V, 3) float64 metres, faces (F, 3) int64)`` pairs.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence

import numpy as np

from pipeline.errors import AssetError
from pipeline.robots.description import Geometry, Link
from pipeline.robots.mesh_io import MeshContext, read_mesh, simplify_mesh, simplify_within
from pipeline.shapes.primitives import box_mesh, cylinder_mesh, sphere_mesh

__all__ = [
    "CAD_MIN_FACES", "PRIMITIVE_CHOICES", "PRIMITIVE_SIZE_CHOICES", "cad_face_budget", "concatenate", "link_mesh",
    "resolved_primitive", "volume_sized",
]

logger = logging.getLogger(__name__)

PRIMITIVE_CHOICES = ("auto", "collision", "box", "cylinder", "hull", "cad")
PRIMITIVE_SIZE_CHOICES = ("bbox", "volume")
CAD_MIN_FACES = 100  # a "cad" link's face budget never falls below this, however small its surface


def link_mesh(
    link: Link,
    primitive: str,
    context: MeshContext,
    *,
    cad_faces: int = 3000,
    cad_faces_per_cm2: float | None = None,
    cad_tolerance_m: float | None = None,
    hull_faces: int = 300,
) -> tuple[np.ndarray, np.ndarray] | None:
    """The link's mesh in its link frame, ``(verts (V, 3), faces (F, 3))``, or ``None`` if it has no geometry.

    ``cad_faces`` / ``hull_faces``: the face budget of a link's mesh in ``"cad"`` / ``"hull"`` mode;
    ``cad_faces_per_cm2``: in ``"cad"`` mode, the budget per square centimetre of the link's surface (see
    :func:`cad_face_budget`); ``cad_tolerance_m``: in ``"cad"`` mode, that budget doubled until the link's
    silhouettes stray at most this far from its full mesh's (:func:`pipeline.robots.mesh_io.simplify_within`;
    ``None``: the budget alone)."""
    if primitive == "auto":
        primitive = resolved_primitive(link, primitive)
        logger.info("link %r: %s (auto)", link.name, primitive)
    elements = geometry_elements(link, primitive)
    if primitive == "hull" and elements:
        parts = [
            transformed(read_mesh(e, context) if e.kind == "mesh" else _primitive_mesh(e), e.T_link_geom)
            for e in elements
        ]  # fmt: skip
        return _convex_hull(concatenate(parts), hull_faces, context)
    if primitive == "cad" and elements:
        parts = []
        for e in elements:
            part = read_mesh(e, context) if e.kind == "mesh" else _primitive_mesh(e)
            parts.append(transformed(part, e.T_link_geom))
        verts, faces = concatenate(parts)
        budget = cad_face_budget(verts, faces, cad_faces, cad_faces_per_cm2)
        if cad_tolerance_m is not None:
            return simplify_within(verts, faces, budget, cad_tolerance_m, context.disk_cache)
        return simplify_mesh(verts, faces, budget, context.disk_cache)
    if primitive not in ("cad", "hull") and elements and not link.collisions:
        logger.info("link %r has no collision geometry: using its visual geometry", link.name)
    if not elements:
        return None
    if primitive == "cylinder" and len(elements) == 1 and elements[0].kind == "cylinder":
        return transformed(_primitive_mesh(elements[0]), elements[0].T_link_geom)  # already one cylinder
    if primitive in ("box", "cylinder"):
        T_link_box, extent = _bounding_box(link.name, elements, context)
        if primitive == "box":
            return transformed(box_mesh(extent), T_link_box)
        axis = 2 if np.isclose(extent[2], extent.max()) else int(np.argmax(extent))  # ties keep z
        radius = float(np.delete(extent, axis).max()) / 2.0
        T_box_cyl = np.eye(4)
        T_box_cyl[:3, :3] = _Z_TO_AXIS[axis]
        return transformed(cylinder_mesh(radius, float(extent[axis])), T_link_box @ T_box_cyl)
    meshes = []
    for element in elements:
        if element.kind != "mesh":
            meshes.append(transformed(_primitive_mesh(element), element.T_link_geom))
        else:
            logger.info("link %r: collision mesh %s replaced by its convex hull", link.name, element.filename)
            meshes.append(transformed(_convex_hull(read_mesh(element, context), hull_faces, context), element.T_link_geom))
    return concatenate(meshes)


def cad_face_budget(verts: np.ndarray, faces: np.ndarray, cad_faces: int, cad_faces_per_cm2: float | None) -> int:
    """A link mesh's face budget in ``"cad"`` mode: ``cad_faces_per_cm2`` times its surface area in cm^2, rounded
    up, clipped to ``[CAD_MIN_FACES, cad_faces]``; ``cad_faces`` if ``cad_faces_per_cm2`` is ``None``.

    Args:
        verts: ``(V, 3)`` metres.
        faces: ``(F, 3)`` indices.
    """
    if cad_faces_per_cm2 is None:
        return cad_faces
    import trimesh

    area_cm2 = float(trimesh.triangles.area(verts[faces]).sum()) * 1e4
    return int(min(cad_faces, max(CAD_MIN_FACES, math.ceil(cad_faces_per_cm2 * area_cm2))))


#: grids tried, coarser each time, when the decimation alone leaves a hull above its budget (:func:`_convex_hull`):
#: cells along each side of the hull's bounding box
HULL_THINNING_CELLS = (64, 32, 16, 8, 4)


def _convex_hull(mesh: tuple[np.ndarray, np.ndarray], face_budget: int, context: MeshContext
                 ) -> tuple[np.ndarray, np.ndarray]:
    """The convex hull of a mesh's vertices, decimated to at most ``face_budget`` faces and made convex again
    (decimation may dent it): closed, outward, close to the mesh's outline.

    A hull of long slivers defeats the quadric decimation (a cylinder of 2000 sections keeps all its 7996 faces; seven
    of Unitree Z1's nine links kept 414-1958 faces of a budget of 300 until 2026-12-02). Where it leaves more than the
    budget, the hull of its vertices thinned to one per cell of a grid (:data:`HULL_THINNING_CELLS` cells along each
    side of its bounding box, 64 first, then coarser) is decimated instead, until the budget is met (or the coarsest grid's
    result is kept)."""
    import trimesh

    hull = trimesh.convex.convex_hull(mesh[0])
    points = np.asarray(hull.vertices, dtype=np.float64)
    candidate = hull
    for cells in (None, *HULL_THINNING_CELLS):
        if cells is not None:
            candidate = trimesh.convex.convex_hull(_grid_thinned(points, cells))
        verts, _ = simplify_mesh(np.asarray(candidate.vertices, dtype=np.float64),
                                 np.asarray(candidate.faces, dtype=np.int64), face_budget, context.disk_cache)
        out = trimesh.convex.convex_hull(verts)
        if len(out.faces) <= face_budget:
            break
    return np.asarray(out.vertices, dtype=np.float64), np.asarray(out.faces, dtype=np.int64)


def _grid_thinned(points: np.ndarray, cells: int) -> np.ndarray:
    """``points (N, 3)``, one (the first) per cell of a grid of ``cells`` cells along each side of their bounding
    box, in their order (each side's extreme points are kept: a thin plate keeps both faces)."""
    low = points.min(0)
    size = np.maximum(np.ptp(points, axis=0), 1e-12) / cells  # (3,)
    _, first = np.unique(np.floor((points - low) / size).astype(np.int64), axis=0, return_index=True)
    return points[np.sort(first)]


def resolved_primitive(link: Link, primitive: str) -> str:
    """``primitive`` with ``"auto"`` resolved for ``link``: ``"hull"`` when its visual geometry includes a mesh,
    else ``"collision"``; any other choice as it is."""
    if primitive != "auto":
        return primitive
    return "hull" if any(e.kind == "mesh" for e in link.visuals) else "collision"


def geometry_elements(link: Link, primitive: str) -> list[Geometry]:
    """The elements a link's mesh is built from: its collision ones (its visual ones for ``"cad"``), else the
    others."""
    if primitive in ("cad", "hull"):
        return list(link.visuals or link.collisions)
    return list(link.collisions or link.visuals)


def volume_sized(link: Link, primitive: str, mesh: tuple[np.ndarray, np.ndarray], context: MeshContext
                  ) -> tuple[np.ndarray, np.ndarray]:
    """The link's one-primitive ``mesh`` scaled about its bounding-box centre to the volume of the link's geometry
    (summed over its elements, as closed meshes: primitives meshed, mesh files read); unchanged, with a warning,
    where an element's mesh is not closed."""
    import trimesh

    volume = 0.0
    for element in geometry_elements(link, primitive):
        verts, faces = read_mesh(element, context) if element.kind == "mesh" else _primitive_mesh(element)
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


def _bounding_box(name: str, elements: Sequence[Geometry], context: MeshContext) -> tuple[np.ndarray, np.ndarray]:
    """``(T_link_box (4, 4), extent (3,))``: a box around the elements, centred at ``T_link_box``'s origin."""
    if len(elements) == 1:
        T_geom_box, extent = _element_box(elements[0], context)
        return elements[0].T_link_geom @ T_geom_box, extent
    corners = []
    for element in elements:
        T_geom_box, extent = _element_box(element, context)
        signs = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64)
        corners.append(transform_points(element.T_link_geom @ T_geom_box, signs * extent / 2))  # (8, 3)
    points = np.concatenate(corners)
    lo, hi = points.min(axis=0), points.max(axis=0)
    T_link_box = np.eye(4)
    T_link_box[:3, 3] = (lo + hi) / 2
    logger.debug("link %r: %d elements bounded by one box in the link frame", name, len(elements))
    return T_link_box, hi - lo


def _element_box(element: Geometry, context: MeshContext) -> tuple[np.ndarray, np.ndarray]:
    """``(T_geom_box (4, 4), extent (3,))``: the element's bounding box in its own frame."""
    T = np.eye(4)
    if element.kind == "box":
        return T, np.array(element.size)
    if element.kind == "cylinder":
        radius, length = element.size
        return T, np.array([2 * radius, 2 * radius, length])
    if element.kind == "sphere":
        return T, np.full(3, 2 * element.size[0])
    if element.kind == "capsule":
        radius, length = element.size
        return T, np.array([2 * radius, 2 * radius, length + 2 * radius])
    if element.kind == "ellipsoid":
        return T, 2 * np.array(element.size)
    verts, _ = read_mesh(element, context)
    lo, hi = verts.min(axis=0), verts.max(axis=0)
    T[:3, 3] = (lo + hi) / 2
    extent = hi - lo
    if not (extent > 0).all():
        raise AssetError(f"mesh {element.filename!r}: flat or empty (bounding box {extent.tolist()} m)")
    return T, extent


def _primitive_mesh(element: Geometry) -> tuple[np.ndarray, np.ndarray]:
    if element.kind == "box":
        return box_mesh(element.size)
    if element.kind == "cylinder":
        return cylinder_mesh(*element.size)
    if element.kind == "capsule":  # trimesh's capsule: closed, outward, along z, centred
        import trimesh

        radius, length = element.size
        capsule = trimesh.creation.capsule(height=length, radius=radius, count=[16, 16])
        return np.asarray(capsule.vertices, dtype=np.float64), np.asarray(capsule.faces, dtype=np.int64)
    if element.kind == "ellipsoid":  # a unit icosphere stretched along its axes
        verts, faces = sphere_mesh(1.0)
        return verts * np.asarray(element.size), faces
    return sphere_mesh(element.size[0])



def transformed(mesh: tuple[np.ndarray, np.ndarray], T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    verts, faces = mesh
    return transform_points(T, verts), faces


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    return points @ T[:3, :3].T + T[:3, 3]  # (N, 3)


def concatenate(meshes: Sequence[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    offsets = np.cumsum([0] + [len(v) for v, _ in meshes[:-1]])
    verts = np.concatenate([v for v, _ in meshes])
    faces = np.concatenate([f + o for (_, f), o in zip(meshes, offsets)])
    return verts, faces

