"""Closed tube meshes around centrelines (the soft continuum robot's surface).

Convention: the surface is ``S(s, phi) = p(s) + r(s) (-N(s) cos(phi) + B(s) sin(phi))`` with ``(T, N, B)`` the
right-handed frames of ``pipeline.shapes.frames`` and ``phi_j = 2 pi j / n_angles``. Vertex order is ring-major:
vertex ``i * n_angles + j`` is ring ``i`` (``i = 0`` at the base ``s = 0``, ``i = n_rings - 1`` at the tip
``s = 1``), angle ``j``; then the base cap centre ``p(0)`` (index ``n_rings * n_angles``) and the tip cap centre
``p(1)`` (index ``n_rings * n_angles + 1``). Faces wind counter-clockwise seen from outside (normals point out), so
the mesh is watertight with positive volume whenever it does not intersect itself.
"""

from __future__ import annotations

import math

import torch

from pipeline.checks import check_shape
from pipeline.errors import ConfigError
from pipeline.shapes.frames import Frames, bezier_frames

__all__ = ["tube_faces", "tube_vertices", "bezier_tube_vertices", "taper_radii", "ring_parameters"]


def tube_faces(n_rings: int, n_angles: int, device: torch.device | None = None) -> torch.Tensor:
    """Triangles of a capped tube; build once and reuse for every batch and iteration.

    Args:
        n_rings: rings along the tube (``>= 2``).
        n_angles: vertices per ring (``>= 3``).
        device: device of the result (``None``: torch's default device).

    Returns:
        ``(F, 3)`` int64 vertex indices, ``F = 2 * n_angles * (n_rings - 1) + 2 * n_angles`` (sides, then base
        cap, then tip cap); vertex order as in the module docstring.
    """
    _check_counts(n_rings, n_angles)
    i = torch.arange(n_rings - 1, device=device)[:, None]  # (R-1, 1)
    j = torch.arange(n_angles, device=device)[None, :]  # (1, A)
    j_next = (j + 1) % n_angles
    a = i * n_angles + j  # ring i, angle j; (R-1, A)
    b = (i + 1) * n_angles + j  # ring i+1, angle j
    c = i * n_angles + j_next  # ring i, angle j+1
    d = (i + 1) * n_angles + j_next  # ring i+1, angle j+1
    sides = torch.stack([torch.stack([a, b, c], -1), torch.stack([c, b, d], -1)], dim=2)  # (R-1, A, 2, 3)
    base_centre = n_rings * n_angles
    tip_centre = base_centre + 1
    ring = torch.arange(n_angles, device=device)
    ring_next = (ring + 1) % n_angles
    last = (n_rings - 1) * n_angles
    base_cap = torch.stack([torch.full_like(ring, base_centre), ring, ring_next], -1)  # (A, 3), normal -T
    tip_cap = torch.stack([torch.full_like(ring, tip_centre), last + ring_next, last + ring], -1)  # normal +T
    return torch.cat([sides.reshape(-1, 3), base_cap, tip_cap]).to(torch.int64)


def tube_vertices(centerline: torch.Tensor, frames: Frames, radii: torch.Tensor, n_angles: int) -> torch.Tensor:
    """Vertices of capped tubes around sampled centrelines (faces from ``tube_faces(S, n_angles)``).

    Args:
        centerline: ``(B, S, 3)`` ring centres from base to tip (camera frame, metres), ``S >= 2``.
        frames: ``Frames`` at those samples, fields ``(B, S, 3)``.
        radii: ``(B, S)`` ring radii (metres).
        n_angles: vertices per ring (``>= 3``).

    Returns:
        ``(B, S * n_angles + 2, 3)`` vertices: rings (ring-major), then ``centerline[:, 0]`` and
        ``centerline[:, -1]`` as cap centres.
    """
    dims = check_shape(centerline, ("B", "S", 3), "centerline")
    for name, field in zip(Frames._fields, frames):
        check_shape(field, (dims["B"], dims["S"], 3), f"frames.{name}")
    check_shape(radii, (dims["B"], dims["S"]), "radii")
    _check_counts(dims["S"], n_angles)
    phi = torch.arange(n_angles, dtype=centerline.dtype, device=centerline.device) * (2.0 * math.pi / n_angles)
    cos, sin = torch.cos(phi)[:, None], torch.sin(phi)[:, None]  # (A, 1)
    # (B, S, 1, 3) * (A, 1) -> (B, S, A, 3)
    direction = -frames.normal[:, :, None, :] * cos + frames.binormal[:, :, None, :] * sin
    rings = centerline[:, :, None, :] + radii[:, :, None, None] * direction  # (B, S, A, 3)
    caps = centerline[:, [0, -1]]  # (B, 2, 3)
    return torch.cat([rings.reshape(dims["B"], -1, 3), caps], dim=1)


def ring_parameters(n_rings: int, *, dtype: torch.dtype, device: torch.device | None = None) -> torch.Tensor:
    """Curve parameters of the rings: ``(n_rings,)`` evenly spaced from 0 (base) to 1 (tip), ends included."""
    _check_counts(n_rings, 3)
    return torch.linspace(0.0, 1.0, n_rings, dtype=dtype, device=device)


def bezier_tube_vertices(
    control_points: torch.Tensor, radii: torch.Tensor, n_angles: int = 40, frame_method: str = "rmf"
) -> torch.Tensor:
    """Tube vertices around Bezier centrelines; rings at ``s = ring_parameters(n_rings)``.

    Args:
        control_points: ``(B, n+1, 3)`` control points (camera frame, metres).
        radii: ``(B, n_rings)`` ring radii (metres), base to tip; ``n_rings`` sets the ring count (paper: 100).
        n_angles: vertices per ring (paper: 40).
        frame_method: ``"rmf"`` (default, defined everywhere) or ``"frenet"`` (raises on straight parts).

    Returns:
        ``(B, n_rings * n_angles + 2, 3)`` vertices for ``tube_faces(n_rings, n_angles)``.
    """
    check_shape(radii, (control_points.shape[0], "R"), "radii")
    s = ring_parameters(radii.shape[1], dtype=control_points.dtype, device=control_points.device)
    points, frames = bezier_frames(control_points, s, frame_method)
    return tube_vertices(points, frames, radii, n_angles)


def taper_radii(
    base_radius_m: float,
    tip_radius_m: float,
    n_rings: int,
    *,
    dtype: torch.dtype = torch.float32,
    device: torch.device | None = None,
) -> torch.Tensor:
    """Linear radius profile from the base ring to the tip ring: ``(n_rings,)`` metres."""
    for name, value in (("base radius", base_radius_m), ("tip radius", tip_radius_m)):
        if not float(value) > 0 or not math.isfinite(float(value)):
            raise ConfigError(f"{name} must be > 0 m, got {value!r}")
    s = ring_parameters(n_rings, dtype=dtype, device=device)
    return base_radius_m + (tip_radius_m - base_radius_m) * s


def _check_counts(n_rings: int, n_angles: int) -> None:
    if isinstance(n_rings, bool) or not isinstance(n_rings, int) or n_rings < 2:
        raise ConfigError(f"n_rings: expected an int >= 2, got {n_rings!r}")
    if isinstance(n_angles, bool) or not isinstance(n_angles, int) or n_angles < 3:
        raise ConfigError(f"n_angles: expected an int >= 3, got {n_angles!r}")
