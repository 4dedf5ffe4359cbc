"""``pipeline.synth.pose.coverage_mask``: the benchmark masks' renderer (supersampled point coverage)."""

import math

import numpy as np

from pipeline.synth.pose import coverage_mask


def _naive_coverage(triangles: np.ndarray, image_size: tuple[int, int], n: int) -> np.ndarray:
    """Every sample of every pixel against every triangle, in plain loops."""
    H, W = image_size
    out = np.zeros((H, W), dtype=bool)
    for v in range(H):
        for u in range(W):
            hits = 0
            for sy in range(n):
                for sx in range(n):
                    px, py = u - 0.5 + (sx + 0.5) / n, v - 0.5 + (sy + 0.5) / n
                    for a, b, c in triangles:
                        d = [(q[0] - p[0]) * (py - p[1]) - (q[1] - p[1]) * (px - p[0])
                             for p, q in ((a, b), (b, c), (c, a))]
                        if min(d) >= 0 or max(d) <= 0:  # either orientation, edges included
                            hits += 1
                            break
            out[v, u] = 2 * hits >= n * n
    return out


def test_coverage_matches_a_naive_loop():
    """Triangles of both orientations, partly outside the image, tiny and large: the same pixels as plain loops."""
    rng = np.random.default_rng(3)
    triangles = np.concatenate([rng.uniform(-4.0, 26.0, (5, 3, 2)),  # large, some crossing the border
                                rng.uniform(5.0, 15.0, (1, 1, 2)) + rng.uniform(-1.5, 1.5, (8, 3, 2))])  # small
    got = coverage_mask(triangles, (18, 22), samples=4)
    assert got.any() and not got.all()
    np.testing.assert_array_equal(got, _naive_coverage(triangles, (18, 22), 4))
    # a small memory bound: the large triangles one by one in bands of rows
    np.testing.assert_array_equal(coverage_mask(triangles, (18, 22), samples=4, chunk=64), got)


def test_coverage_of_a_polygon_is_unbiased():
    """A regular 90-gon (fan of triangles): the mask's pixel count is its exact area to within 2 pixels (OpenCV's
    ``fillConvexPoly`` at 8x, the benchmark's renderer until 2026-11-24, fills every sample an edge touches: about
    a sixteenth of a pixel too much along the outline, here 26 pixels)."""
    n, radius, centre = 90, 83.3, np.array([151.3, 118.6])
    angles = 2 * math.pi * np.arange(n) / n
    ring = centre + radius * np.stack([np.cos(angles), np.sin(angles)], axis=1)
    triangles = np.stack([np.broadcast_to(centre, (n, 2)), ring, np.roll(ring, -1, axis=0)], axis=1)
    area = 0.5 * n * radius**2 * math.sin(2 * math.pi / n)
    mask = coverage_mask(triangles, (240, 320))
    assert abs(int(mask.sum()) - area) < 2.0
    # the fan's inner edges leave no gaps: every pixel whose centre is 1 px inside is set
    v, u = np.mgrid[:240, :320]
    assert mask[np.hypot(u - centre[0], v - centre[1]) < radius - 1.0].all()


def test_a_hand_held_cameras_sway_is_smooth_bounded_and_leaves_the_rest_of_the_video_as_it_was():
    """``manipulator_sequence(handheld_deg=...)``: the same joints and steady poses as without it (the sway is drawn
    last), each frame turned by at most the sway's bound (two sines of ``handheld_deg / 2`` per component) and moved
    by at most ``handheld_deg`` cm per component, smoothly (no frame-to-frame jump above what 15-frame sines give)."""
    from pathlib import Path

    import pytest
    from scipy.spatial.transform import Rotation

    from pipeline.camera import Camera
    from pipeline.errors import ConfigError
    from pipeline.robots import load_robot
    from pipeline.synth.pose import manipulator_sequence

    model = load_robot(Path(__file__).resolve().parents[2] / "models/robots/toy_arm/toy_arm.urdf", "base_link")
    camera = Camera(K=((500.0, 0.0, 319.5), (0.0, 500.0, 179.5), (0.0, 0.0, 1.0)), width=640, height=360)
    joints, steady = manipulator_sequence(model, camera, np.random.default_rng(5), 60, orbit_deg_per_frame=0.5)
    joints_h, swayed = manipulator_sequence(model, camera, np.random.default_rng(5), 60, orbit_deg_per_frame=0.5,
                                            handheld_deg=2.0)
    np.testing.assert_array_equal(joints_h, joints)
    H = swayed @ np.linalg.inv(steady)  # (F, 4, 4) the sway, about each camera's centre
    angles = np.degrees(Rotation.from_matrix(H[:, :3, :3]).as_rotvec())  # (F, 3)
    assert np.abs(angles).max() <= 2.0 * math.sqrt(3) and np.abs(angles).max() > 0.5  # there, and bounded
    assert np.abs(H[:, :3, 3]).max() <= 0.02 + 1e-12 and np.abs(H[:, :3, 3]).max() > 0.005
    step = np.abs(np.diff(angles, axis=0)).max()
    assert step <= 2.0 * 2.0 * math.pi / 15.0 * 1.01  # |d/dk| of two sines of amplitude 1 and period >= 15
    np.testing.assert_allclose(H[:, 3], np.tile([0.0, 0.0, 0.0, 1.0], (60, 1)), atol=1e-12)
    with pytest.raises(ConfigError, match="handheld_deg"):
        manipulator_sequence(model, camera, np.random.default_rng(5), 3, handheld_deg=-1.0)
