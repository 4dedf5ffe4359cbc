"""Closed triangle meshes of boxes, cylinders and spheres, subdivided so per-vertex offsets have freedom.

Convention:
    Metres. Each primitive is centred at the origin of its own frame, like URDF geometry: a box spans
    ``[-size/2, size/2]``, a cylinder's axis is ``z`` and it spans ``z in [-length/2, length/2]``. Meshes are
    watertight (every edge shared by exactly two faces, vertices shared, no duplicates) and wound counter-clockwise
    seen from outside, so face normals ``(v1 - v0) x (v2 - v0)`` point outwards. Each function returns
    ``(verts, faces)``: ``(V, 3)`` float64 and ``(F, 3)`` int64 numpy arrays (geometry assets, built once on
    load; the robot model turns them into tensors).

Subdivision (defaults), chosen so every face of a primitive has interior vertices an offset can move:
    box: 4 x 4 quads per side (98 vertices, 192 faces); cylinder: 24 segments around, 4 sections along the axis,
    2 rings per cap (170 vertices, 336 faces); sphere: an icosahedron subdivided twice (162 vertices, 320 faces).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from pipeline.checks import check_positive
from pipeline.errors import ConfigError


# Not trimesh.creation.box / cylinder: they have no interior vertices (8 / 50), so offsets could move only corners.
def box_mesh(size: Sequence[float], subdivisions: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """Box centred at the origin with edges along the axes, each side a grid of quads split into two triangles.

    Args:
        size: ``(3,)`` edge lengths ``(x, y, z)``, metres, all > 0.
        subdivisions: quads along every edge (>= 1), the same for all edges.

    Returns:
        ``verts (6 n^2 + 2, 3)`` with ``n = subdivisions``, ``faces (12 n^2, 3)``.
    """
    sizes = _float_triple(size, "size")
    n = _count(subdivisions, "subdivisions", minimum=1)
    steps = np.arange(n + 1)
    lattice = np.stack(np.meshgrid(steps, steps, steps, indexing="ij"), axis=-1)  # (n+1, n+1, n+1, 3)
    on_surface = ((lattice == 0) | (lattice == n)).any(axis=-1)  # (n+1, n+1, n+1)
    vertex_id = np.full(on_surface.shape, -1, dtype=np.int64)
    vertex_id[on_surface] = np.arange(int(on_surface.sum()))
    verts = (lattice[on_surface] / n - 0.5) * np.asarray(sizes)  # (V, 3)

    a, b = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    a, b = a.ravel(), b.ravel()  # (n*n,) quad corners along the in-plane axes u, v
    faces = []
    for axis in range(3):
        u, v = (axis + 1) % 3, (axis + 2) % 3  # u x v = +axis, so (u, v) counter-clockwise seen from +axis
        for side in (0, n):

            def corner(du: int, dv: int) -> np.ndarray:
                coords = [None, None, None]
                coords[axis] = np.full_like(a, side)
                coords[u], coords[v] = a + du, b + dv
                return vertex_id[coords[0], coords[1], coords[2]]  # (n*n,)

            p00, p10, p11, p01 = corner(0, 0), corner(1, 0), corner(1, 1), corner(0, 1)
            quads = np.concatenate([np.stack([p00, p10, p11], 1), np.stack([p00, p11, p01], 1)])  # (2 n^2, 3)
            faces.append(quads if side == n else quads[:, ::-1])
    return verts, np.ascontiguousarray(np.concatenate(faces), dtype=np.int64)


def cylinder_mesh(
    radius: float, length: float, segments: int = 24, *, sections: int = 4, cap_rings: int = 2
) -> tuple[np.ndarray, np.ndarray]:
    """Closed cylinder along ``z``, centred at the origin: a prism with ``segments`` sides and flat capped ends.

    Args:
        radius: metres, > 0 (vertices lie on the circle; the prism is inscribed).
        length: metres, > 0, along ``z``.
        segments: vertices around the circumference (>= 3).
        sections: rings of quads along the axis (>= 1).
        cap_rings: concentric rings of each cap, counting the rim (>= 1; 1 is a plain triangle fan).

    Returns:
        ``verts (segments * (sections + 1 + 2 (cap_rings - 1)) + 2, 3)``, ``faces (2 segments (sections + 2
        cap_rings - 1), 3)``.
    """
    r = check_positive(radius, "radius")
    h = check_positive(length, "length")
    m = _count(segments, "segments", minimum=3)
    n_sections = _count(sections, "sections", minimum=1)
    n_rings = _count(cap_rings, "cap_rings", minimum=1)

    angle = 2.0 * np.pi * np.arange(m) / m
    circle = np.stack([np.cos(angle), np.sin(angle)], axis=1)  # (m, 2)
    rings = []  # (radius fraction, z) of each ring of m vertices
    rings += [(1.0, -h / 2 + h * k / n_sections) for k in range(n_sections + 1)]
    rings += [(c / n_rings, -h / 2) for c in range(n_rings - 1, 0, -1)]  # bottom cap, outside in
    rings += [(c / n_rings, h / 2) for c in range(n_rings - 1, 0, -1)]  # top cap, outside in
    ring_verts = [np.column_stack([circle * r * frac, np.full(m, z)]) for frac, z in rings]
    verts = np.concatenate(ring_verts + [np.array([[0.0, 0.0, -h / 2], [0.0, 0.0, h / 2]])])
    ring_index = np.arange(len(rings) * m).reshape(len(rings), m)  # (rings, m)
    bottom_centre, top_centre = len(rings) * m, len(rings) * m + 1

    def band(outer: np.ndarray, inner: np.ndarray) -> np.ndarray:
        # quad (outer_j, outer_j+1, inner_j+1, inner_j); counter-clockwise seen from outside when `inner` lies at
        # +z of `outer` on the side wall, or nearer the axis on the top cap
        o0, o1 = outer, np.roll(outer, -1)
        i0, i1 = inner, np.roll(inner, -1)
        return np.concatenate([np.stack([o0, o1, i1], 1), np.stack([o0, i1, i0], 1)])  # (2m, 3)

    def fan(ring: np.ndarray, centre: int) -> np.ndarray:
        return np.stack([ring, np.roll(ring, -1), np.full(m, centre)], 1)  # (m, 3)

    side = [band(ring_index[k], ring_index[k + 1]) for k in range(n_sections)]
    bottom_chain = [ring_index[0]] + [ring_index[n_sections + 1 + c] for c in range(n_rings - 1)]
    top_chain = [ring_index[n_sections]] + [ring_index[n_sections + n_rings + c] for c in range(n_rings - 1)]
    top = [band(top_chain[c], top_chain[c + 1]) for c in range(n_rings - 1)] + [fan(top_chain[-1], top_centre)]
    bottom = [band(bottom_chain[c], bottom_chain[c + 1]) for c in range(n_rings - 1)]
    bottom += [fan(bottom_chain[-1], bottom_centre)]
    faces = np.concatenate(side + top + [f[:, ::-1] for f in bottom])  # the bottom cap faces -z
    return verts, np.ascontiguousarray(faces, dtype=np.int64)


def sphere_mesh(radius: float, subdivisions: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """Icosphere centred at the origin: an icosahedron whose faces are split in four ``subdivisions`` times.

    Args:
        radius: metres, > 0 (vertices lie on the sphere).
        subdivisions: rounds of 1-to-4 splits (>= 0).

    Returns:
        ``verts (10 * 4^s + 2, 3)``, ``faces (20 * 4^s, 3)`` with ``s = subdivisions``.
    """
    r = check_positive(radius, "radius")
    rounds = _count(subdivisions, "subdivisions", minimum=0)
    g = (1.0 + 5.0**0.5) / 2.0
    verts = np.array(
        [[-1, g, 0], [1, g, 0], [-1, -g, 0], [1, -g, 0], [0, -1, g], [0, 1, g],
         [0, -1, -g], [0, 1, -g], [g, 0, -1], [g, 0, 1], [-g, 0, -1], [-g, 0, 1]],
        dtype=np.float64,
    )  # fmt: skip
    faces = np.array(
        [[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4], [11, 10, 2],
         [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5], [2, 4, 11],
         [6, 2, 10], [8, 6, 7], [9, 8, 1]],
        dtype=np.int64,
    )  # fmt: skip
    for _ in range(rounds):
        edges = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)  # (3F, 2): ab, bc, ca per face
        unique_edges, edge_of = np.unique(edges, axis=0, return_inverse=True)
        midpoints = verts[unique_edges].mean(axis=1)  # (E, 3)
        mid = (len(verts) + edge_of.reshape(-1, 3)).T  # (3, F): index of the midpoint of ab, bc, ca
        a, b, c = faces.T
        ab, bc, ca = mid
        faces = np.concatenate([np.stack(t, 1) for t in ((a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca))])
        verts = np.concatenate([verts, midpoints])
        verts = verts / np.linalg.norm(verts, axis=1, keepdims=True)  # back onto the sphere every round
    verts = r * verts / np.linalg.norm(verts, axis=1, keepdims=True)
    return verts, np.ascontiguousarray(faces, dtype=np.int64)


def _float_triple(values: Sequence[float], name: str) -> tuple[float, float, float]:
    try:
        triple = tuple(float(v) for v in values)
    except (TypeError, ValueError):
        raise ConfigError(f"{name}: expected three positive numbers, got {values!r}") from None
    if len(triple) != 3:
        raise ConfigError(f"{name}: expected three positive numbers, got {values!r}")
    for i, v in enumerate(triple):
        check_positive(v, f"{name}[{i}]")
    return triple  # type: ignore[return-value]


def _count(value: int, name: str, *, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise ConfigError(f"{name}: expected an int >= {minimum}, got {value!r}")
    return int(value)
