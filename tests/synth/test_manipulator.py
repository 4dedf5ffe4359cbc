from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from pipeline.errors import ConfigError, ShapeError
from pipeline.render import render_hard
from pipeline.robots.manipulator import load_urdf_robot
from pipeline.synth.manipulator import (
    Lighting,
    random_background,
    random_camera_pose,
    random_colors,
    random_intrinsics,
    random_joint_angles,
    random_manipulator_image,
    randomize_photometric,
    render_mesh_image,
)

URDF = Path(__file__).resolve().parents[2] / "models" / "robots" / "toy_arm" / "toy_arm.urdf"


@pytest.fixture(scope="module")
def toy_arm():
    return load_urdf_robot(URDF, "base_link")


def test_manipulator_image_truth_is_consistent(toy_arm):
    sample = random_manipulator_image(toy_arm, np.random.default_rng(0), (120, 160))
    assert sample.image.shape == (120, 160, 3) and sample.image.dtype == np.uint8
    assert sample.mask.shape == (120, 160) and sample.mask.dtype == bool
    assert 200 < sample.mask.sum() < 0.9 * sample.mask.size
    # the mask is the hard silhouette of the mesh at the returned joint angles and pose
    q = torch.from_numpy(sample.joint_angles)[None]
    verts = toy_arm.mesh_in_root(q)[0].numpy() @ sample.T_cam_root[:3, :3].T + sample.T_cam_root[:3, 3]
    again = render_hard(torch.from_numpy(verts)[None], toy_arm.faces, torch.from_numpy(sample.K), (120, 160))[0]
    np.testing.assert_array_equal(again.numpy(), sample.mask)
    # the whole robot is in view: the border rows and columns stay free
    assert not (sample.mask[0].any() or sample.mask[-1].any() or sample.mask[:, 0].any() or sample.mask[:, -1].any())
    assert (sample.joint_angles >= toy_arm.joint_lower.numpy()).all()
    assert (sample.joint_angles <= toy_arm.joint_upper.numpy()).all()


def test_same_seed_same_image(toy_arm):
    a = random_manipulator_image(toy_arm, np.random.default_rng(5), (60, 80))
    b = random_manipulator_image(toy_arm, np.random.default_rng(5), (60, 80))
    np.testing.assert_array_equal(a.image, b.image)
    np.testing.assert_array_equal(a.mask, b.mask)


def test_camera_pose_sees_every_point():
    rng = np.random.default_rng(1)
    points = rng.uniform(-0.2, 0.2, (50, 3)) + [0.0, 0.0, 0.5]
    K = random_intrinsics(rng, (90, 120))
    for _ in range(5):
        T = random_camera_pose(points, K, (90, 120), rng, margin_px=3.0)
        np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-12)
        cam = points @ T[:3, :3].T + T[:3, 3]
        uv = cam[:, :2] / cam[:, 2:] * K[0, 0] + K[:2, 2]
        assert (cam[:, 2] > 0).all() and (uv >= 3.0 - 1e-9).all()
        assert (uv[:, 0] <= 116.0 + 1e-9).all() and (uv[:, 1] <= 86.0 + 1e-9).all()
    with pytest.raises(ConfigError, match="no camera pose kept the robot in the 120x90 image"):
        random_camera_pose(points, K, (90, 120), rng, fill_range=(5.0, 6.0), max_tries=5)


def test_background_keeps_away_from_robot_colours():
    rng = np.random.default_rng(2)
    robot = np.array([[40.0, 40.0, 220.0]])  # red
    image = random_background(rng, (100, 120), robot)
    lab = cv2.cvtColor(image, cv2.COLOR_BGR2LAB).reshape(-1, 3).astype(float)
    robot_lab = cv2.cvtColor(np.uint8([robot]), cv2.COLOR_BGR2LAB)[0, 0].astype(float)
    distance = np.linalg.norm(lab[:, 1:] - robot_lab[1:], axis=1)
    assert np.percentile(distance, 1) > 10.0  # anti-aliased edges aside, nothing shares the robot's chroma


def test_render_mesh_image_shading_and_errors():
    verts = np.array([[-0.1, -0.1, 1.0], [0.1, -0.1, 1.0], [0.0, 0.1, 1.0]])
    faces = np.array([[0, 2, 1]])  # normal towards the camera (-z)
    K = np.array([[100.0, 0, 31.5], [0, 100.0, 31.5], [0, 0, 1]])
    background = np.zeros((64, 64, 3), np.uint8)
    image, mask = render_mesh_image(verts, faces, np.array([[0.0, 0.0, 200.0]]), K, background,
                                    Lighting(direction_cam=(0.0, 0.0, -1.0), ambient=0.5, diffuse=0.5))  # fmt: skip
    assert mask.sum() > 100 and not background.any()
    inside = image[mask & (cv2.erode(mask.astype(np.uint8), np.ones((3, 3))) > 0)]
    np.testing.assert_array_equal(inside, [[0, 0, 200]] * len(inside))  # full light: the base colour
    with pytest.raises(ShapeError, match="face_colors_bgr: expected"):
        render_mesh_image(verts, faces, np.zeros((2, 3)), K, background)
    with pytest.raises(ShapeError, match="behind the camera"):
        render_mesh_image(verts - [0, 0, 2], faces, np.zeros((1, 3)), K, background)


def test_random_helpers(toy_arm):
    rng = np.random.default_rng(3)
    colours = random_colors(rng, 20)
    assert colours.shape == (20, 3) and colours.min() >= 0 and colours.max() <= 255
    q = random_joint_angles(toy_arm, rng)
    assert q.shape == (len(toy_arm.joint_names),)
    image = np.full((30, 40, 3), 128, np.uint8)
    out = randomize_photometric(image, rng)
    assert out.shape == image.shape and out.dtype == np.uint8 and not np.shares_memory(out, image)
