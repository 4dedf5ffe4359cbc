import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from pipeline.camera import load_camera
from pipeline.errors import ConfigError, ShapeError
from pipeline.io import read_image, read_mask
from pipeline.preprocess import arc_length_keypoints, clean_mask, skeleton_path
from pipeline.shapes.polyline import bezier_centerline, polyline_arc_length, resample_polyline
from pipeline.synth.soft_arm import (DEFAULT_ARM_COLOR_BGR, pcc_arm, pcc_centerline, place_in_view, random_bezier_arm,
                                     render_tube_image)

H, W = 240, 320
K = np.array([[300.0, 0.0, 159.5], [0.0, 300.0, 119.5], [0.0, 0.0, 1.0]])


def project(points):
    uvw = points @ K.T
    return uvw[:, :2] / uvw[:, 2:3]


@pytest.mark.parametrize("order", [1, 2, 3])
def test_random_bezier_arm_length_and_view(order):
    cp = random_bezier_arm(np.random.default_rng(order), K, (H, W), length_m=0.2, distance_m=0.45, order=order)
    assert cp.shape == (order + 1, 3) and cp.dtype == np.float64
    centreline = bezier_centerline(cp, 201)
    assert polyline_arc_length(centreline)[-1] == pytest.approx(0.2, rel=1e-5)
    uv = project(centreline)
    assert (uv >= 20 - 1e-9).all() and (uv[:, 0] <= W - 21 + 1e-9).all() and (uv[:, 1] <= H - 21 + 1e-9).all()
    assert np.linalg.norm(centreline.mean(0)) == pytest.approx(0.45, rel=1e-3)
    border = np.minimum(np.minimum(uv[:, 0], uv[:, 1]), np.minimum(W - 1 - uv[:, 0], H - 1 - uv[:, 1]))
    assert border[0] <= border[-1] - 10  # base nearer the image border than the tip


def test_random_arm_is_seeded():
    a = random_bezier_arm(np.random.default_rng(7), K, (H, W), distance_m=0.5)
    b = random_bezier_arm(np.random.default_rng(7), K, (H, W), distance_m=0.5)
    c = random_bezier_arm(np.random.default_rng(8), K, (H, W), distance_m=0.5)
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, c)


def test_random_arm_that_cannot_fit_raises():
    with pytest.raises(ConfigError, match="make the arm shorter"):
        random_bezier_arm(np.random.default_rng(0), K, (H, W), length_m=2.0, distance_m=0.3, max_tries=5)


def test_pcc_single_arc_is_a_circle_arc():
    points = pcc_arm(np.random.default_rng(3), K, (H, W), n_segments=1, length_m=0.2, distance_m=0.5, n_points=101)
    assert points.shape == (101, 3)
    assert polyline_arc_length(points)[-1] == pytest.approx(0.2, rel=1e-4)
    chords = np.linalg.norm(points[10:] - points[:-10], axis=1)  # equal arcs on a circle have equal chords
    assert chords.std() < 1e-6 * chords.mean()
    centred = points - points.mean(0)
    assert np.linalg.svd(centred, compute_uv=False)[2] < 1e-9  # planar


def test_pcc_two_segments_differ_from_one_circle():
    points = pcc_arm(np.random.default_rng(4), K, (H, W), n_segments=2, distance_m=0.5)
    first, second = points[:50], points[51:]
    c1 = np.linalg.norm(first[10:] - first[:-10], axis=1)
    c2 = np.linalg.norm(second[10:] - second[:-10], axis=1)
    assert c1.std() < 1e-5 * c1.mean() and c2.std() < 1e-5 * c2.mean()  # constant curvature on each
    assert abs(c1.mean() - c2.mean()) > 1e-6  # but not the same curvature


def ray_cast_cylinder(z0, r, length):
    """Exact silhouette of a capped cylinder along x, centred at (0, 0, z0), by one ray per pixel centre."""
    v, u = np.mgrid[0:H, 0:W].astype(float)
    d = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)  # rays, z = 1
    # Side: (t dy)^2 + (t dz - z0)^2 = r^2, with |t dx| <= L/2 at a root.
    a = d[..., 1] ** 2 + d[..., 2] ** 2
    b = -2 * z0 * d[..., 2]
    c = z0**2 - r**2
    disc = b**2 - 4 * a * c
    root = np.sqrt(np.maximum(disc, 0))
    side = np.zeros((H, W), bool)
    for t in ((-b - root) / (2 * a), (-b + root) / (2 * a)):
        side |= (disc >= 0) & (np.abs(t * d[..., 0]) <= length / 2)
    caps = np.zeros((H, W), bool)
    for x in (-length / 2, length / 2):
        t = x / d[..., 0]
        caps |= (t * d[..., 1]) ** 2 + (t * d[..., 2] - z0) ** 2 <= r**2
    return side | caps


def test_render_straight_cylinder_matches_ray_cast_silhouette():
    z, r, length = 0.5, 0.02, 0.2
    centreline = np.stack([np.linspace(-0.1, 0.1, 101) + 0.01, np.zeros(101), np.full(101, z)], 1)
    image, mask = render_tube_image(centreline, np.full(101, r), K, (H, W), np.random.default_rng(0))
    assert image.shape == (H, W, 3) and image.dtype == np.uint8
    assert mask.shape == (H, W) and mask.dtype == bool
    expected = ray_cast_cylinder(z, r, length)
    expected = np.roll(expected, 6, axis=1)  # the 0.01 m shift in x is 6 px at this depth
    iou = (mask & expected).sum() / (mask | expected).sum()
    assert iou > 0.98


def test_render_is_seeded_and_arm_has_its_colour():
    rng = np.random.default_rng(5)
    cp = random_bezier_arm(rng, K, (H, W), distance_m=0.5)
    centreline = bezier_centerline(cp, 101)
    radii = np.linspace(0.015, 0.007, 101)
    image, mask = render_tube_image(centreline, radii, K, (H, W), np.random.default_rng(1))
    again, mask2 = render_tube_image(centreline, radii, K, (H, W), np.random.default_rng(1))
    np.testing.assert_array_equal(image, again)
    np.testing.assert_array_equal(mask, mask2)
    assert (clean_mask(mask) == mask).all()  # one component, no holes
    uv = np.round(project(centreline)).astype(int)
    assert mask[uv[:, 1], uv[:, 0]].all()
    hsv = cv2.cvtColor(image, cv2.COLOR_BGR2HSV).astype(float)
    arm_hue = cv2.cvtColor(np.uint8([[DEFAULT_ARM_COLOR_BGR]]), cv2.COLOR_BGR2HSV)[0, 0, 0]
    near = np.abs((hsv[..., 0] - arm_hue + 90) % 180 - 90) <= 8
    saturated = hsv[..., 1] > 100
    assert (near & saturated)[mask].mean() > 0.9
    assert (near & saturated)[~mask].mean() < 0.02


def test_rendered_mask_gives_keypoints_on_the_projected_centreline():
    rng = np.random.default_rng(11)
    cp = random_bezier_arm(rng, K, (H, W), distance_m=0.5)
    centreline = bezier_centerline(cp, 101)
    _, mask = render_tube_image(centreline, np.full(101, 0.01), K, (H, W), rng)
    truth_uv = resample_polyline(project(centreline), 400)
    path = skeleton_path(clean_mask(mask))  # default rule: the base is the end nearer the image border
    points, _ = arc_length_keypoints(path, k=4)
    expected, _ = arc_length_keypoints(truth_uv, k=4)
    # The mask's ends lie beyond the projected end centres p(0), p(1) by up to the radius (6 px here) where an
    # end cap is seen obliquely, which also stretches the path a little; keypoints stay within a few pixels.
    error = np.linalg.norm(points - expected, axis=1)
    assert error[:-1].max() < 4.0 and error[-1] < 6.0 + 1.0


def test_render_errors():
    line = np.stack([np.zeros(5), np.zeros(5), np.linspace(-0.1, 0.1, 5)], 1)
    with pytest.raises(ShapeError, match="behind the camera"):
        render_tube_image(line, np.full(5, 0.01), K, (H, W), np.random.default_rng(0))
    with pytest.raises(ShapeError, match="radii_m"):
        render_tube_image(line + [0, 0, 1], np.full(4, 0.01), K, (H, W), np.random.default_rng(0))


@pytest.mark.parametrize("name", ["quadratic", "cubic_s", "pcc"])
def test_bundled_examples_are_consistent(name):
    folder = Path(__file__).resolve().parents[2] / "data" / "soft_arm" / name
    camera = load_camera(folder / "camera.json")
    truth = json.loads((folder / "truth.json").read_text())
    mask = read_mask(folder / "mask.png", camera.image_size)
    assert read_image(folder / "image.png").shape == (*camera.image_size, 3)
    centreline = np.asarray(truth["centerline_cam_m"])
    assert centreline.shape == (101, 3) and len(truth["radii_m"]) == 101
    assert polyline_arc_length(centreline)[-1] == pytest.approx(truth["length_m"], rel=1e-3)
    if truth["model"] == "bezier":
        control_points = np.asarray(truth["control_points_cam_m"])
        np.testing.assert_allclose(bezier_centerline(control_points, 101), centreline, atol=1e-9)
    uvw = centreline @ camera.K_array().T
    uv = np.round(uvw[:, :2] / uvw[:, 2:]).astype(int)
    assert mask[uv[:, 1], uv[:, 0]].all()


def test_pcc_centerline_against_circular_arcs():
    """One section: every point on the circle of radius 1/k through the base, tangent to +z there, and the chord
    2 sin(k L / 2) / k; two opposite sections (an S): the tip tangent is the base's again; straight when k = 0."""
    k, L = 12.0, 0.1
    arc = pcc_centerline([k], [0.0], [L], 201)
    assert polyline_arc_length(arc)[-1] == pytest.approx(L, rel=1e-4)
    assert np.linalg.norm(arc[-1] - arc[0]) == pytest.approx(2.0 * np.sin(k * L / 2.0) / k, rel=1e-6)
    assert np.abs(arc[:, 0]).max() < 1e-12  # plane angle 0: bends about body x, stays in the y-z plane
    centre = np.array([0.0, -1.0 / k, 0.0]) if arc[-1, 1] < 0 else np.array([0.0, 1.0 / k, 0.0])
    np.testing.assert_allclose(np.linalg.norm(arc - centre, axis=1), 1.0 / k, rtol=1e-6)
    s_shape = pcc_centerline([k, k], [0.0, np.pi], [L, L], 401)
    tangent = s_shape[-1] - s_shape[-2]
    assert tangent / np.linalg.norm(tangent) == pytest.approx([0.0, 0.0, 1.0], abs=1e-2)
    np.testing.assert_allclose(pcc_centerline([0.0], [1.0], [L], 5)[:, 2], np.linspace(0.0, L, 5), atol=1e-12)
    with pytest.raises(ConfigError, match="as many curvatures"):
        pcc_centerline([k, k], [0.0], [L, L])


def test_place_in_view_keeps_the_shape_and_the_view():
    local = pcc_centerline([10.0, 10.0], [0.0, 2.0], [0.1, 0.1], 101)
    cam = place_in_view(np.random.default_rng(3), local, K, (H, W), distance_m=0.45)
    np.testing.assert_allclose(np.linalg.norm(cam[1:] - cam[:-1], axis=1),
                               np.linalg.norm(local[1:] - local[:-1], axis=1), rtol=1e-9)  # a rigid motion
    uv = project(cam)
    assert (uv >= 20.0 - 1e-9).all() and (uv[:, 0] <= W - 21).all() and (uv[:, 1] <= H - 21).all()
    assert np.linalg.norm(cam.mean(axis=0)) == pytest.approx(0.45, rel=1e-9)


@pytest.mark.parametrize("order", [2, 3])
def test_moving_arm_keeps_base_length_and_view_and_bends_both_ways(order):
    from pipeline.synth.soft_arm import moving_bezier_arm

    H, W = 180, 320
    K = np.array([[175.0, 0.0, (W - 1) / 2], [0.0, 175.0, (H - 1) / 2], [0.0, 0.0, 1.0]])
    control = moving_bezier_arm(np.random.default_rng(4), K, (H, W), 24, order=order, period_frames=12.0)
    assert control.shape == (24, order + 1, 3)
    np.testing.assert_allclose(control[:, 0], np.broadcast_to(control[0, 0], (24, 3)), atol=1e-12)  # fixed base
    first_leg = control[:, 1] - control[:, 0]
    first_leg /= np.linalg.norm(first_leg, axis=1, keepdims=True)
    np.testing.assert_allclose(first_leg, np.broadcast_to(first_leg[0], (24, 3)), atol=1e-9)  # fixed direction
    turns = []
    for c in control:
        line = bezier_centerline(c, 401)
        assert abs(polyline_arc_length(line)[-1] - 0.2) < 1e-4  # length within 0.05 % (the 401-point polyline)
        uv = line @ K.T
        uv = uv[:, :2] / uv[:, 2:]
        assert uv.min() >= 19.0 and (uv[:, 0] <= W - 1 - 19.0).all() and (uv[:, 1] <= H - 1 - 19.0).all()
        border = np.minimum(np.minimum(uv[:, 0], uv[:, 1]), np.minimum(W - 1 - uv[:, 0], H - 1 - uv[:, 1]))
        assert border[0] <= border[-1] - 9.0  # the base nearer the border than the tip (skeleton_path's rule)
        legs = np.diff(c, axis=0)
        normal = np.cross(legs[0], legs[1])  # the first joint's turn, signed along the base's bending axis
        turns.append(normal)
    signs = np.sign(np.array(turns) @ np.array(turns)[0])
    assert (signs > 0).any() and (signs < 0).any()  # the first joint bends one way, then the other


def test_moving_pcc_arm_keeps_its_base_sections_and_view():
    """The moving two-section arm: base point and direction fixed, each frame the constant-curvature centreline of
    its curvatures and planes (``pcc_centerline``, placed rigidly), curvatures within the peak and swinging through 0
    (each section bends one way, then the other), every frame in view with the base nearer the border."""
    from pipeline.synth.soft_arm import moving_pcc_arm

    H, W = 180, 320
    K = np.array([[175.0, 0.0, (W - 1) / 2], [0.0, 175.0, (H - 1) / 2], [0.0, 0.0, 1.0]])
    lines, curvatures, planes = moving_pcc_arm(np.random.default_rng(4), K, (H, W), 30, period_frames=12.0)
    assert lines.shape == (30, 101, 3) and curvatures.shape == planes.shape == (30, 2)
    assert (curvatures >= 0).all() and curvatures.max() <= 15.0 and curvatures.min(axis=0).max() < 4.0
    np.testing.assert_allclose(lines[:, 0], np.broadcast_to(lines[0, 0], (30, 3)), atol=1e-12)  # fixed base
    start = lines[:, 1] - lines[:, 0]
    start /= np.linalg.norm(start, axis=1, keepdims=True)
    assert (start @ start[0] > 0.999).all()  # the base direction (2 mm out) barely turns
    for line, k, a in zip(lines, curvatures, planes):
        assert abs(polyline_arc_length(line)[-1] - 0.2) < 1e-3
        local = pcc_centerline(list(k), list(a), [0.1, 0.1], 101)  # the same shape, rigidly moved
        np.testing.assert_allclose(np.linalg.norm(local[:, None] - local[None], axis=-1),
                                   np.linalg.norm(line[:, None] - line[None], axis=-1), atol=1e-9)
        uv = line @ K.T
        uv = uv[:, :2] / uv[:, 2:]
        assert uv.min() >= 19.0 and (uv[:, 0] <= W - 1 - 19.0).all() and (uv[:, 1] <= H - 1 - 19.0).all()
        border = np.minimum(np.minimum(uv[:, 0], uv[:, 1]), np.minimum(W - 1 - uv[:, 0], H - 1 - uv[:, 1]))
        assert border[0] <= border[-1] - 9.0
    with pytest.raises(ConfigError, match="sections: expected an int >= 1"):
        moving_pcc_arm(np.random.default_rng(0), K, (H, W), 3, sections=0)


def test_area_averaged_drawing_covers_the_true_area():
    # A triangle of known area painted white on grey: the summed coverage is its area to within 0.15 px times its
    # perimeter (OpenCV's non-anti-aliased fill at 4x keeps samples on the edge: +0.11 px measured); OpenCV's
    # anti-aliased fill, the default path of render_tube_image, widens it by about 0.66 px.
    from pipeline.synth.soft_arm import _draw_area_averaged

    triangle = np.array([[[20.3, 30.1], [180.7, 40.2], [60.2, 170.9]]])
    (x1, y1), (x2, y2) = triangle[0, 1] - triangle[0, 0], triangle[0, 2] - triangle[0, 0]
    area = 0.5 * abs(x1 * y2 - y1 * x2)
    perimeter = sum(np.linalg.norm(triangle[0, i] - triangle[0, (i + 1) % 3]) for i in range(3))
    image = np.full((200, 200, 3), 55, np.uint8)  # grey: the coverage is (value - 55) / 200
    _draw_area_averaged(image, triangle, np.array([[255.0, 255.0, 255.0]]), 4)
    excess = (image[..., 0].astype(float) - 55.0).sum() / 200.0 - area  # px of area beyond the triangle's
    assert 0.0 < excess < 0.15 * perimeter
    aa = np.zeros((200, 200), np.uint8)
    cv2.fillConvexPoly(aa, np.round(triangle[0] * 16).astype(np.int32), 255, lineType=cv2.LINE_AA, shift=4)
    assert 0.5 * perimeter < aa.sum() / 255.0 - area < 0.8 * perimeter


def test_supersampled_render_keeps_the_background_and_the_mask():
    rng = np.random.default_rng(5)
    centreline = bezier_centerline(random_bezier_arm(rng, K, (H, W), distance_m=0.5), 101)
    radii = np.linspace(0.015, 0.007, 101)
    image, mask = render_tube_image(centreline, radii, K, (H, W), np.random.default_rng(1))
    fine, fine_mask = render_tube_image(centreline, radii, K, (H, W), np.random.default_rng(1), supersample=4)
    np.testing.assert_array_equal(mask, fine_mask)
    changed = np.abs(image.astype(int) - fine.astype(int)).max(-1) > 0  # the arm's pixels (shading, rim)
    # within 4 px of the arm (the anti-aliased fill reaches 1 px beyond the mask, the 3x3 blur 1 px more)
    near = cv2.dilate(mask.astype(np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (9, 9))) > 0
    assert changed.any() and not (changed & ~near).any()
    with pytest.raises(ConfigError, match="supersample: expected an int >= 1"):
        render_tube_image(centreline, radii, K, (H, W), np.random.default_rng(1), supersample=0)
