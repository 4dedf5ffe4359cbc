"""Metrics that compare estimates with ground truth (DESIGN.md 1.1 for the soft arm, 1.2 for manipulators).

Convention: camera frame (OpenCV: x right, y down, z forward), metres in, pixels and millimetres out; numpy
float64 arrays (evaluation runs on finished results, outside autograd).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.spatial.transform import Rotation

from pipeline.errors import ConfigError, ShapeError
from pipeline.shapes.polyline import polyline_arc_length, resample_polyline

__all__ = ["centerline_errors", "point_errors", "pck", "pose_errors", "rim_offset_px"]


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


def point_errors(
    T_cam_root_est: np.ndarray, T_cam_root_true: np.ndarray, points_root: np.ndarray, K: np.ndarray
) -> dict[str, np.ndarray]:
    """Errors of a point fixed on the robot (e.g. the end effector) over many cases, in 3D (mm) and 2D (px).

    Each case ``n`` maps the point ``points_root[n]`` (root frame; for a point given in a link frame, the caller
    applies the known ``T_root_link(q_n)`` first) to the camera with the estimated and the true ``T_cam_root``
    and compares: 3D Euclidean distance in mm, and the distance in pixels between the pinhole projections with
    ``K`` (no distortion).

    Args:
        T_cam_root_est: ``(N, 4, 4)`` estimated poses, metres.
        T_cam_root_true: ``(N, 4, 4)`` true poses, metres.
        points_root: ``(N, 3)`` the point in each case's root frame, metres.
        K: ``(3, 3)`` intrinsics shared by all cases, or ``(N, 3, 3)``, pixels.

    Returns:
        ``{"err_3d_mm": (N,), "err_2d_px": (N,)}``.

    Raises:
        ShapeError: bad shapes, non-finite values, or a true point at or behind the camera.
    """
    T_est = _transforms(T_cam_root_est, "T_cam_root_est")
    T_true = _transforms(T_cam_root_true, "T_cam_root_true")
    N = T_est.shape[0]
    if T_true.shape[0] != N:
        raise ShapeError(f"T_cam_root_true: expected {N} cases like T_cam_root_est, got {T_true.shape[0]}")
    points = np.asarray(points_root, dtype=np.float64)
    if points.shape != (N, 3) or not np.isfinite(points).all():
        raise ShapeError(f"points_root: expected finite ({N}, 3), got {points.shape}")
    K = np.asarray(K, dtype=np.float64)
    if K.shape == (3, 3):
        K = np.broadcast_to(K, (N, 3, 3))
    if K.shape != (N, 3, 3) or not np.isfinite(K).all():
        raise ShapeError(f"K: expected a finite (3, 3) or ({N}, 3, 3) matrix, got {K.shape}")
    est = np.einsum("nij,nj->ni", T_est[:, :3, :3], points) + T_est[:, :3, 3]  # (N, 3)
    true = np.einsum("nij,nj->ni", T_true[:, :3, :3], points) + T_true[:, :3, 3]
    if (true[:, 2] <= 0).any():
        raise ShapeError("points_root: a true point lies at or behind the camera (z <= 0)")

    def project(p: np.ndarray) -> np.ndarray:
        h = np.einsum("nij,nj->ni", K, p)
        z = np.where(np.abs(h[:, 2:3]) > 1e-12, h[:, 2:3], 1e-12)  # an estimate behind the camera: far away
        return h[:, :2] / z

    return {"err_3d_mm": np.linalg.norm(est - true, axis=1) * 1000.0,
            "err_2d_px": np.linalg.norm(project(est) - project(true), axis=1)}


def mask_iou(mask: np.ndarray, truth: np.ndarray) -> float:
    """Intersection over union of two ``(H, W)`` bool masks (1.0 when both are empty).

    Raises:
        ShapeError: the masks are not bool arrays of the same shape.
    """
    for name, m in (("mask", mask), ("truth", truth)):
        if not isinstance(m, np.ndarray) or m.dtype != bool or m.ndim != 2:
            raise ShapeError(f"{name}: expected an (H, W) bool array, got {getattr(m, 'dtype', type(m).__name__)} "
                             f"{getattr(m, 'shape', '')}")
    if mask.shape != truth.shape:
        raise ShapeError(f"mask {mask.shape} and truth {truth.shape} differ in size")
    union = int((mask | truth).sum())
    return 1.0 if union == 0 else int((mask & truth).sum()) / union


def rim_offset_px(mask: np.ndarray, truth: np.ndarray) -> float:
    """How far ``mask``'s outline lies outside ``truth``'s on average, pixels: the area it adds (or, negative,
    takes away) over the true outline's length (OpenCV's contours, holes' included:
    ``pipeline.preprocess.outline_length``). A segmenter's rim bias, as the soft-arm fit takes it (``ShapeFitConfig.rim_offset_px``):
    measure it on a few frames with true masks and take the median. False positives and misses away from the
    outline count too.

    Raises:
        ShapeError: the masks are not bool arrays of the same shape, or ``truth`` is empty.
    """
    mask_iou(mask, truth)  # the same checks
    if not truth.any():
        raise ShapeError("truth: the true mask is empty (no outline to measure the rim against)")
    import cv2

    from pipeline.preprocess import outline_length

    contours, _ = cv2.findContours(truth.astype(np.uint8), cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
    return (int(mask.sum()) - int(truth.sum())) / max(outline_length(contours), 1.0)


def pck(errors: np.ndarray, thresholds: Sequence[float]) -> np.ndarray:
    """Percentage of correct keypoints: the fraction of ``errors`` ``(N,)`` at or below each threshold.

    Returns:
        ``(T,)`` fractions in [0, 1], one per threshold (same units as ``errors``). NaN errors count as wrong.
    """
    e = np.asarray(errors, dtype=np.float64).reshape(-1)
    if e.size == 0:
        raise ShapeError("errors: expected at least one case")
    t = np.asarray(thresholds, dtype=np.float64).reshape(-1)
    if t.size == 0 or not np.isfinite(t).all() or (t < 0).any():
        raise ConfigError(f"thresholds: expected finite numbers >= 0, got {list(thresholds)}")
    ok = np.nan_to_num(e, nan=np.inf)[None, :] <= t[:, None]  # (T, N)
    return ok.mean(axis=1)


def pose_errors(T_cam_root_est: np.ndarray, T_cam_root_true: np.ndarray) -> dict[str, np.ndarray]:
    """Rotation and translation errors of estimated ``T_cam_root`` over many cases.

    Rotation: the geodesic angle of ``R_est^T R_true`` in degrees. Translation: ``|t_est - t_true|`` in mm, i.e.
    the error of the root origin in the camera frame (it grows with the distance of the root from the robot's
    middle; compare points on the robot with :func:`point_errors`).

    Args:
        T_cam_root_est, T_cam_root_true: ``(N, 4, 4)``, metres.

    Returns:
        ``{"rotation_deg": (N,), "translation_mm": (N,)}``.
    """
    T_est = _transforms(T_cam_root_est, "T_cam_root_est")
    T_true = _transforms(T_cam_root_true, "T_cam_root_true")
    if T_true.shape != T_est.shape:
        raise ShapeError(f"T_cam_root_true: expected shape {T_est.shape} like T_cam_root_est, got {T_true.shape}")
    R = Rotation.from_matrix(T_est[:, :3, :3]).inv() * Rotation.from_matrix(T_true[:, :3, :3])  # R_est^T R_true
    return {"rotation_deg": np.degrees(R.magnitude()),
            "translation_mm": np.linalg.norm(T_est[:, :3, 3] - T_true[:, :3, 3], axis=1) * 1000.0}


def _transforms(T: np.ndarray, name: str) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    if T.ndim != 3 or T.shape[1:] != (4, 4) or T.shape[0] < 1:
        raise ShapeError(f"{name}: expected (N, 4, 4) transforms with N >= 1, got {T.shape}")
    if not np.isfinite(T).all():
        raise ShapeError(f"{name}: contains NaN or inf")
    return T
