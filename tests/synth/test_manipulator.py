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


def test_random_colors_saturated_share():
    """``random_colors`` as documented: 75% saturated hues, the rest white, grey or black (low saturation)."""
    colours = random_colors(np.random.default_rng(3), 4000)
    assert colours.shape == (4000, 3) and colours.dtype == np.float64
    hsv = cv2.cvtColor(np.round(colours).astype(np.uint8)[None], cv2.COLOR_BGR2HSV)[0].astype(float)
    saturated = hsv[:, 1] >= 60  # saturated hues are drawn with S >= 90, the neutral ones with S <= 30
    assert 0.72 < saturated.mean() < 0.78  # binomial standard deviation 0.007
    assert (hsv[saturated, 2] >= 85).all() and (hsv[~saturated, 1] <= 35).all()
    assert np.ptp(hsv[saturated, 0]) > 170  # all hues (OpenCV's hue is 0-180)


def test_random_joint_angles_cover_the_limits(toy_arm):
    rng = np.random.default_rng(3)
    lower = np.maximum(toy_arm.joint_lower.numpy(), -np.pi)
    upper = np.minimum(toy_arm.joint_upper.numpy(), np.pi)
    q = np.stack([random_joint_angles(toy_arm, rng) for _ in range(200)])
    assert q.shape == (200, len(toy_arm.joint_names))
    assert (q >= lower).all() and (q <= upper).all()
    assert (np.ptp(q, axis=0) > 0.9 * (upper - lower)).all()  # uniform over the range, not a point


def _photometric_ranges(bright, dark, n=9):
    """What the documented parameter ranges of ``randomize_photometric`` allow for an image of two flat grey
    halves, blur, noise and JPEG aside: per channel x = clip((g w_c - m) k + m + b)^gamma (white balance w_c in
    0.8-1.2, contrast k in 0.7-1.3 about the image mean m after the white balance, brightness b in +-0.12, gamma
    in 0.7-1.4). Returns the (low, high) output level (0-255) of the bright half, of the dark half, and of their
    difference (the contrast), over a grid of ``n`` values per parameter, ends included (the extremes are at
    the corners: a finer grid gives the same to 0.1 level)."""
    axes = [np.linspace(0.8, 1.2, n), np.linspace(1.6, 2.4, n), np.linspace(0.7, 1.3, n),
            np.linspace(-0.12, 0.12, n), np.linspace(0.7, 1.4, n)]  # w_c, the other two w's sum, k, b, gamma
    w_c, w_rest, k, b, gamma = np.meshgrid(*axes, indexing="ij")
    g_bright, g_dark = bright / 255.0, dark / 255.0
    m = (g_bright + g_dark) / 2 * (w_c + w_rest) / 3
    x_bright, x_dark = (255.0 * np.clip((g * w_c - m) * k + m + b, 0.0, 1.0) ** gamma for g in (g_bright, g_dark))
    return [(float(v.min()), float(v.max())) for v in (x_bright, x_dark, x_bright - x_dark)]


def test_randomize_photometric_changes_the_image_within_the_documented_ranges():
    """Over 30 seeds: a new uint8 image each time, different from the input (by more than rounding), different
    from seed to seed, and the level of each flat half and their difference (the contrast) inside what the
    documented brightness, contrast, white-balance and gamma ranges allow (3 levels of slack for noise and
    JPEG)."""
    image = np.full((64, 96, 3), 60, np.uint8)
    image[:, :48] = 190  # a bright and a dark half of equal area, split on the JPEG block grid
    bright_range, dark_range, contrast_range = _photometric_ranges(190, 60)
    interiors = (np.s_[8:56, 8:40], np.s_[8:56, 56:88])  # away from the edge (blur) and its JPEG blocks
    bright_levels = []
    for seed in range(30):
        out = randomize_photometric(image, np.random.default_rng(seed))
        assert out.shape == image.shape and out.dtype == np.uint8 and not np.shares_memory(out, image)
        assert np.abs(out.astype(float) - image).mean() > 2.0, seed
        bright, dark = (out[region].reshape(-1, 3).mean(0) for region in interiors)  # per channel
        for level, (low, high) in ((bright, bright_range), (dark, dark_range), (bright - dark, contrast_range)):
            assert (level > low - 3.0).all() and (level < high + 3.0).all(), (seed, level, low, high)
        bright_levels.append(bright.mean())
    assert np.std(bright_levels) > 8.0  # the brightness really varies with the seed (measured 24)
