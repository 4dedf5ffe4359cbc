"""Description of a soft continuum robot: a tapered tube around a centreline (DESIGN.md 1.1).

The centreline's model (a Bezier curve and its order) is a setting of the fit, ``ShapeFitConfig.order``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from pipeline.errors import ConfigError
from pipeline.shapes.frames import FRAME_METHODS
from pipeline.shapes.tube import taper_radii, tube_faces

__all__ = ["ContinuumRobot"]


@dataclass(frozen=True, kw_only=True)
class ContinuumRobot:
    """What is known about a soft continuum arm before fitting its shape.

    Convention: camera frame (OpenCV: x right, y down, z forward), metres.

    Fields:
        length_m: centreline length from base to tip.
        base_radius_m, tip_radius_m: tube radius at the base and at the tip (linear taper in between).
        base_point_cam_m: the base centre ``p(0)`` if it is known (e.g. from a calibrated mount), or ``None``
            meaning *unknown*: then it is estimated like every other control point.
        base_direction_cam: unit tangent at the base if it is known, or ``None`` meaning *unknown*.
        n_rings: rings of the tube mesh along the centreline (paper: 100).
        n_angles: vertices per ring (paper: 40).
        frame_method: frames along the centreline, ``"rmf"`` (rotation-minimising, default) or ``"frenet"``.
    """

    length_m: float
    base_radius_m: float
    tip_radius_m: float
    base_point_cam_m: tuple[float, float, float] | None = None
    base_direction_cam: tuple[float, float, float] | None = None
    n_rings: int = 100
    n_angles: int = 40
    frame_method: str = "rmf"

    def __post_init__(self) -> None:
        _positive(self.length_m, "length", "m")
        _positive(self.base_radius_m, "base radius", "m")
        _positive(self.tip_radius_m, "tip radius", "m")
        _int_at_least(self.n_rings, 2, "n_rings")
        _int_at_least(self.n_angles, 3, "n_angles")
        if self.frame_method not in FRAME_METHODS:
            raise ConfigError(
                f"frame_method: expected one of {', '.join(map(repr, FRAME_METHODS))}, got {self.frame_method!r}"
            )
        if self.base_point_cam_m is not None:
            object.__setattr__(self, "base_point_cam_m", _vector3(self.base_point_cam_m, "base_point_cam_m"))
        if self.base_direction_cam is not None:
            direction = _vector3(self.base_direction_cam, "base_direction_cam")
            norm = math.sqrt(sum(c * c for c in direction))
            if abs(norm - 1.0) > 1e-6:
                raise ConfigError(f"base_direction_cam must be a unit vector, got {direction} (norm {norm:.6g})")
            object.__setattr__(self, "base_direction_cam", direction)

    def initial_radii_m(
        self, *, dtype: torch.dtype = torch.float32, device: torch.device | None = None
    ) -> torch.Tensor:
        """``(n_rings,)`` linear taper from ``base_radius_m`` to ``tip_radius_m`` (the radii's starting values)."""
        return taper_radii(self.base_radius_m, self.tip_radius_m, self.n_rings, dtype=dtype, device=device)

    def faces(self, device: torch.device | None = None) -> torch.Tensor:
        """``(F, 3)`` int64 faces of the tube mesh (``pipeline.shapes.tube.tube_faces``)."""
        return tube_faces(self.n_rings, self.n_angles, device=device)


def _positive(value: float, name: str, unit: str) -> None:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ConfigError(f"{name} must be a number > 0 {unit}, got {value!r}") from None
    if not (v > 0 and math.isfinite(v)):
        raise ConfigError(f"{name} must be > 0 {unit}, got {value!r}")


def _int_at_least(value: int, low: int, name: str) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or value < low:
        raise ConfigError(f"{name}: expected an int >= {low}, got {value!r}")


def _vector3(value: object, name: str) -> tuple[float, float, float]:
    try:
        x, y, z = (float(c) for c in value)  # type: ignore[union-attr]
    except (TypeError, ValueError):
        raise ConfigError(f"{name}: expected three numbers (x, y, z), got {value!r}") from None
    if not all(math.isfinite(c) for c in (x, y, z)):
        raise ConfigError(f"{name}: expected finite numbers, got {value!r}")
    return (x, y, z)
