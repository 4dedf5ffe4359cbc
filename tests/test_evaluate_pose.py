"""Manipulator metrics: end-effector point errors in 3D and 2D, PCK at thresholds, rotation/translation errors."""

import math

import numpy as np
import pytest

from pipeline.errors import ConfigError, ShapeError
from pipeline.evaluate import pck, point_errors, pose_errors

K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])


def _pose(rotvec=(0.0, 0.0, 0.0), t=(0.0, 0.0, 2.0)) -> np.ndarray:
    import cv2

    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(np.asarray(rotvec, dtype=np.float64))[0]
    T[:3, 3] = t
    return T


def test_point_errors_values():
    truth = np.stack([_pose(), _pose()])
    est = np.stack([_pose(t=(0.01, 0.0, 2.0)), _pose(t=(0.0, 0.0, 2.5))])  # 10 mm sideways; 500 mm deeper
    points = np.zeros((2, 3))
    err = point_errors(est, truth, points, K)
    np.testing.assert_allclose(err["err_3d_mm"], [10.0, 500.0])
    np.testing.assert_allclose(err["err_2d_px"], [500.0 * 0.01 / 2.0, 0.0], atol=1e-9)  # on the optical axis


def test_point_errors_point_in_root_frame_and_per_case_K():
    truth = _pose(rotvec=(0.0, 0.0, math.pi / 2))[None]
    est = _pose()[None]  # 90 degrees off about the optical axis
    point = np.array([[0.1, 0.0, 0.0]])  # 10 cm along the root's x: lands on +y (truth) or +x (estimate)
    err = point_errors(est, truth, point, K[None])
    np.testing.assert_allclose(err["err_3d_mm"], [100.0 * math.sqrt(2)])
    np.testing.assert_allclose(err["err_2d_px"], [500.0 * 0.1 * math.sqrt(2) / 2.0])


def test_pck_fractions_at_thresholds():
    errors = np.array([1.0, 4.0, 6.0, np.nan])
    np.testing.assert_allclose(pck(errors, [0.5, 4.0, 10.0]), [0.0, 0.5, 0.75])  # NaN counts as wrong
    with pytest.raises(ConfigError, match="thresholds"):
        pck(errors, [-1.0])
    with pytest.raises(ShapeError, match="at least one"):
        pck(np.array([]), [1.0])


def test_pose_errors_values_and_symmetry():
    truth = np.stack([_pose(), _pose(rotvec=(0.3, -0.2, 0.1))])
    est = np.stack([_pose(rotvec=(0.0, math.radians(10.0), 0.0), t=(0.0, 0.003, 2.004)), truth[1]])
    err = pose_errors(est, truth)
    np.testing.assert_allclose(err["rotation_deg"], [10.0, 0.0], atol=1e-6)
    np.testing.assert_allclose(err["translation_mm"], [5.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(pose_errors(truth, est)["rotation_deg"], err["rotation_deg"], atol=1e-9)
    near_pi = pose_errors(_pose(rotvec=(0.0, 0.0, math.pi - 1e-7))[None], _pose()[None])["rotation_deg"]
    np.testing.assert_allclose(near_pi, [180.0], atol=1e-4)


def test_bad_inputs():
    T = _pose()[None]
    with pytest.raises(ShapeError, match="T_cam_root_est"):
        point_errors(np.eye(4), T, np.zeros((1, 3)), K)
    with pytest.raises(ShapeError, match="NaN"):
        pose_errors(np.full((1, 4, 4), np.nan), T)
    with pytest.raises(ShapeError, match="points_root"):
        point_errors(T, T, np.zeros((2, 3)), K)
    with pytest.raises(ShapeError, match="behind the camera"):
        point_errors(T, T, np.array([[0.0, 0.0, -3.0]]), K)
    with pytest.raises(ShapeError, match="K"):
        point_errors(T, T, np.zeros((1, 3)), np.eye(2))
