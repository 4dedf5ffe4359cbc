"""Metrics that compare estimates with ground truth (DESIGN.md 1.1 for the soft arm, 1.2 for manipulators).

Convention: camera frame (OpenCV: x right, y down, z forward), metres in, pixels and millimetres out; numpy
float64 arrays (evaluation runs on finished results, outside autograd).
"""

from __future__ import annotations

import numpy as np

from pipeline.errors import ConfigError, ShapeError
from pipeline.shapes.polyline import polyline_arc_length, resample_polyline

__all__ = ["centerline_errors"]


def centerline_errors(
    est_points_cam: np.ndarray, true_points_cam: np.ndarray, K: np.ndarray, n_samples: int = 101
) -> dict[str, float]:
    """Centreline error of a soft-arm estimate, in 3D (mm) and in the image (px).

    Both centrelines are resampled to ``n_samples`` points uniform in their own 3D arc length (point ``k`` at
    the fraction ``k / (n_samples - 1)`` of the length from the base), and compared point by point. The 2D error
    projects those same corresponding points with the pinhole ``K`` (no distortion): ``u = K @ p / z``.

    Args:
        est_points_cam: ``(N, 3)`` estimated centreline, base to tip (camera frame, metres), ``N >= 2``.
        true_points_cam: ``(M, 3)`` true centreline, base to tip (camera frame, metres), ``M >= 2``.
        K: ``(3, 3)`` intrinsics, pixels.
        n_samples: corresponding points compared (``>= 2``).

    Returns:
        ``{"mean_2d_px", "median_2d_px", "max_2d_px", "tip_2d_px", "mean_3d_mm", "median_3d_mm", "max_3d_mm",
        "tip_3d_mm", "length_error_mm", "n_samples"}``; ``tip_*`` compare the last points, ``length_error_mm``
        is estimated minus true length.

    Raises:
        ShapeError: bad shapes, non-finite values, or a point at or behind the camera (z <= 0).
    """
    est = _centerline(est_points_cam, "est_points_cam")
    true = _centerline(true_points_cam, "true_points_cam")
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3) or not np.isfinite(K).all():
        raise ShapeError(f"K: expected a finite (3, 3) matrix, got shape {K.shape}")
    if isinstance(n_samples, bool) or not isinstance(n_samples, int) or n_samples < 2:
        raise ConfigError(f"n_samples: expected an int >= 2, got {n_samples!r}")
    est_s, true_s = resample_polyline(est, n_samples), resample_polyline(true, n_samples)  # (n, 3) each
    d3 = np.linalg.norm(est_s - true_s, axis=1) * 1000.0  # (n,) mm
    d2 = np.linalg.norm(_project(est_s, K) - _project(true_s, K), axis=1)  # (n,) px
    return {
        "mean_2d_px": float(d2.mean()),
        "median_2d_px": float(np.median(d2)),
        "max_2d_px": float(d2.max()),
        "tip_2d_px": float(d2[-1]),
        "mean_3d_mm": float(d3.mean()),
        "median_3d_mm": float(np.median(d3)),
        "max_3d_mm": float(d3.max()),
        "tip_3d_mm": float(d3[-1]),
        "length_error_mm": float(polyline_arc_length(est)[-1] - polyline_arc_length(true)[-1]) * 1000.0,
        "n_samples": n_samples,
    }


def _centerline(points: np.ndarray, name: str) -> np.ndarray:
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or points.shape[0] < 2:
        raise ShapeError(f"{name}: expected (N, 3) with N >= 2, got {points.shape}")
    if not np.isfinite(points).all():
        raise ShapeError(f"{name}: contains NaN or inf")
    if (points[:, 2] <= 0).any():
        raise ShapeError(f"{name}: has points at or behind the camera (z <= 0)")
    return points


def _project(points: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Pinhole projection ``(N, 3)`` metres -> ``(N, 2)`` pixels."""
    homogeneous = points @ K.T  # (N, 3)
    return homogeneous[:, :2] / homogeneous[:, 2:3]
