import json

import cv2
import numpy as np
import pytest
import torch

from pipeline.camera import (
    Camera,
    check_image_matches_camera,
    load_camera,
    project_points,
    resize_camera,
    resize_image,
    save_camera,
    undistort_image,
    working_camera,
    working_size,
)
from pipeline.errors import AssetError, ConfigError, ShapeError

K_ROWS = ((500.0, 0.0, 320.0), (0.0, 480.0, 240.0), (0.0, 0.0, 1.0))


def make_camera(**kw):
    args = dict(K=K_ROWS, width=640, height=480)
    args.update(kw)
    return Camera(**args)


def random_points(B, N, generator, dtype=torch.float64):
    xy = torch.rand(B, N, 2, generator=generator, dtype=dtype) - 0.5
    z = 1.0 + 2.0 * torch.rand(B, N, 1, generator=generator, dtype=dtype)
    return torch.cat([xy * z, z], dim=-1)


# --- Camera -------------------------------------------------------------------------------------------------------


def test_camera_smoke():
    cam = make_camera(dist=[0.1, 0, 0, 0])
    assert cam.image_size == (480, 640)
    assert cam.dist == (0.1, 0.0, 0.0, 0.0)
    assert cam.has_distortion
    assert not make_camera(dist=(0, 0, 0, 0, 0)).has_distortion
    assert hash(cam) == hash(make_camera(dist=(0.1, 0, 0, 0)))
    K = cam.K_tensor(dtype=torch.float32)
    assert K.shape == (3, 3) and K.dtype == torch.float32
    assert K[0, 0] == 500 and K[1, 2] == 240
    assert cam.with_image_size((240, 320)) == resize_camera(cam, (240, 320))


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        (dict(K=((1, 0, 0), (0, 1, 0))), "3x3"),
        (dict(K="abc"), "3x3"),
        (dict(K=((500, 0, 320), (0, 480, 240), (0, 1, 1))), "last row"),
        (dict(K=((-500, 0, 320), (0, 480, 240), (0, 0, 1))), "fx"),
        (dict(K=((500, 0, 320), (0, 0, 240), (0, 0, 1))), "fy"),
        (dict(K=((500, 1, 320), (0, 480, 240), (0, 0, 1))), "skew"),
        (dict(K=((500, 0, float("nan")), (0, 480, 240), (0, 0, 1))), "finite"),
        (dict(width=0), "width: expected a positive int"),
        (dict(height=2.5), "height: expected a positive int"),
        (dict(dist=(0.1, 0.2, 0.3)), "expected 0, 4, 5, 8, 12, 14 coefficients"),
        (dict(dist=(0.1, 0.2, float("inf"), 0)), "dist: expected finite"),
    ],
)
def test_camera_invalid(kwargs, message):
    with pytest.raises(ConfigError, match=message):
        make_camera(**kwargs)


def test_check_image_matches_camera():
    cam = make_camera()
    check_image_matches_camera((480, 640), cam)
    with pytest.raises(ConfigError, match="camera is 640x480 but image is 320x240"):
        check_image_matches_camera((240, 320), cam)


# --- JSON file ----------------------------------------------------------------------------------------------------


def test_save_load_roundtrip(tmp_path):
    cam = resize_camera(make_camera(dist=(0.1, -0.2, 0.001, 0.002, 0.03)), (333, 517))
    path = tmp_path / "sub" / "cam.json"
    save_camera(cam, path)
    assert load_camera(path) == cam
    data = json.loads(path.read_text())
    assert set(data) == {"K", "dist", "width", "height"}
    assert data["width"] == 517 and data["height"] == 333


def test_load_without_dist(tmp_path):
    path = tmp_path / "cam.json"
    path.write_text(json.dumps({"K": [list(r) for r in K_ROWS], "width": 640, "height": 480}))
    assert load_camera(path).dist == ()


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("{not json", "not valid JSON"),
        ("[1, 2]", "expected a JSON object"),
        ('{"K": [[1,0,0],[0,1,0],[0,0,1]], "width": 4}', "missing key 'height'"),
        ('{"K": [[1,0,0],[0,1,0],[0,0,1]], "width": 4, "height": 4, "distortion": []}', "unknown key.*'distortion'"),
        ('{"K": [[1,0,0],[0,1,0],[0,0,1]], "width": 4, "height": 4, "dist": [1, 2]}', "dist: expected"),
        ('{"K": [[1,0,0],[0,1,0]], "width": 4, "height": 4}', "K: expected a 3x3"),
    ],
)
def test_load_invalid(tmp_path, text, message):
    path = tmp_path / "cam.json"
    path.write_text(text)
    with pytest.raises(ConfigError, match=message):
        load_camera(path)


def test_load_missing(tmp_path):
    with pytest.raises(AssetError, match="camera file not found: .*nope.json"):
        load_camera(tmp_path / "nope.json")


# --- projection ---------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("B", [1, 3])
def test_project_points_matches_opencv(B):
    g = torch.Generator().manual_seed(0)
    points = random_points(B, 20, g)
    Ks = torch.stack([make_camera().K_tensor(), resize_camera(make_camera(), (100, 150)).K_tensor()] * 2)[:B]
    uv = project_points(points, Ks)
    assert uv.shape == (B, 20, 2) and uv.dtype == torch.float64
    for b in range(B):
        ref, _ = cv2.projectPoints(points[b].numpy(), np.zeros(3), np.zeros(3), Ks[b].numpy(), np.zeros(5))
        np.testing.assert_allclose(uv[b].numpy(), ref[:, 0, :], atol=1e-4)
    # a shared (3, 3) K broadcasts over the batch
    per_item = torch.stack([project_points(points[b : b + 1], Ks[0])[0] for b in range(B)])
    torch.testing.assert_close(project_points(points, Ks[0]), per_item)


def test_project_points_float32_follows_input():
    points = random_points(2, 5, torch.Generator().manual_seed(1), dtype=torch.float32)
    uv = project_points(points, make_camera().K_tensor(dtype=torch.float32))
    assert uv.dtype == torch.float32


def test_project_points_invalid():
    K = make_camera().K_tensor()
    with pytest.raises(ShapeError, match=r"points_cam: expected shape \(B, N, 3\), got \(5, 3\)"):
        project_points(torch.zeros(5, 3, dtype=torch.float64), K)
    with pytest.raises(ShapeError, match="K: expected shape"):
        project_points(torch.zeros(2, 5, 3, dtype=torch.float64), torch.eye(3, dtype=torch.float64).expand(3, 3, 3))
    with pytest.raises(ShapeError, match="K: expected dtype torch.float32"):
        project_points(torch.ones(1, 5, 3), K)
    with pytest.raises(ConfigError, match="min_depth"):
        project_points(torch.ones(1, 5, 3, dtype=torch.float64), K, min_depth=0.0)


def test_project_points_gradcheck():
    points = random_points(2, 4, torch.Generator().manual_seed(2)).requires_grad_()
    K = make_camera().K_tensor().expand(2, 3, 3).clone().requires_grad_()
    assert torch.autograd.gradcheck(project_points, (points, K))


def test_project_points_at_and_behind_camera_finite():
    points = torch.tensor([[[0.1, 0.2, 0.0], [0.1, -0.2, -1.0], [0.0, 0.0, 0.0], [0.1, 0.1, 1e-9]]])
    points = points.double().requires_grad_()
    uv = project_points(points, make_camera().K_tensor())
    assert torch.isfinite(uv).all()
    (grad,) = torch.autograd.grad(uv.sum(), points)
    assert torch.isfinite(grad).all()
    assert (grad[..., 2] == 0).all()  # depth clamped: no gradient through z
    # clamped to min_depth = 1e-6: u = fx * x / 1e-6 + cx
    assert uv[0, 0, 0].item() == pytest.approx(500 * 0.1 / 1e-6 + 320)


# --- resizing -----------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("size", [(240, 320), (100, 250), (960, 1280)])
def test_resize_camera_formula(size):
    cam = make_camera()
    small = resize_camera(cam, size)
    assert small.image_size == size
    sx, sy = size[1] / 640, size[0] / 480
    points = random_points(2, 10, torch.Generator().manual_seed(3))
    uv = project_points(points, cam.K_tensor())
    uv_small = project_points(points, small.K_tensor())
    expected = torch.stack([(uv[..., 0] + 0.5) * sx - 0.5, (uv[..., 1] + 0.5) * sy - 0.5], dim=-1)
    torch.testing.assert_close(uv_small, expected)


def test_resize_camera_matches_cv2_resize_of_a_disk():
    cam = Camera(K=((800.0, 0.0, 400.0), (0.0, 800.0, 300.0), (0.0, 0.0, 1.0)), width=800, height=600)
    point = torch.tensor([[[0.013, -0.021, 1.0]]], dtype=torch.float64)
    u, v = project_points(point, cam.K_tensor())[0, 0].tolist()
    shift = 4  # draw at sub-pixel precision
    image = np.zeros((600, 800), np.uint8)
    cv2.circle(image, (round(u * 2**shift), round(v * 2**shift)), 40 * 2**shift, 255, -1, cv2.LINE_AA, shift)
    for size in [(150, 200), (240, 320), (97, 131)]:
        small = cv2.resize(image.astype(np.float64), (size[1], size[0]), interpolation=cv2.INTER_AREA)
        rows, cols = np.indices(small.shape)
        centroid = np.array([(cols * small).sum(), (rows * small).sum()]) / small.sum()
        expected = project_points(point, resize_camera(cam, size).K_tensor())[0, 0].numpy()
        np.testing.assert_allclose(centroid, expected, atol=0.05)


def test_resize_camera_invalid():
    with pytest.raises(ConfigError, match=r"image_size: expected \(H, W\)"):
        resize_camera(make_camera(), (0, 10))


def test_working_camera():
    cam = make_camera()
    assert working_camera(cam, 1000) is cam
    small = working_camera(cam, 320)
    assert small.image_size == (240, 320) and small == resize_camera(cam, (240, 320))
    assert working_size((480, 640), 101) == (76, 101)  # 480 * 101 / 640 = 75.75 -> 76
    assert working_size((1, 1000), 10) == (1, 10)
    with pytest.raises(ConfigError, match="max_side"):
        working_camera(cam, 0)


def test_resize_image_and_mask():
    image = np.random.default_rng(0).integers(0, 255, (48, 64, 3), dtype=np.uint8)
    out = resize_image(image, (24, 32), is_mask=False)
    assert out.shape == (24, 32, 3) and out.dtype == np.uint8
    np.testing.assert_allclose(out[0, 0], image[:2, :2].reshape(4, 3).mean(0), atol=1)
    mask = np.zeros((4, 4), bool)
    mask[0, :2] = True  # half of the top-left 2x2 block -> kept
    mask[2, 2] = True  # a quarter of the bottom-right block -> dropped
    small = resize_image(mask, (2, 2), is_mask=True)
    assert small.dtype == bool
    np.testing.assert_array_equal(small, [[True, False], [False, False]])
    with pytest.raises(ShapeError, match=r"mask: expected an \(H, W\) bool array, got uint8"):
        resize_image(mask.astype(np.uint8), (2, 2), is_mask=True)


# --- undistortion -------------------------------------------------------------------------------------------------


def test_undistort_image():
    dist = (-0.2, 0.05, 0.001, -0.001, 0.0)
    cam = make_camera(dist=dist)
    # a distorted image of one bright pixel at where the undistorted pixel (400, 300) is seen
    undist_uv = np.array([[[400.0, 300.0]]])
    normalised = cv2.undistortPoints(undist_uv, cam.K_array(), np.zeros(5))  # (1, 1, 2) in normalised coords
    xyz = np.concatenate([normalised[0], np.ones((1, 1))], axis=-1)
    dist_uv, _ = cv2.projectPoints(xyz, np.zeros(3), np.zeros(3), cam.K_array(), np.array(dist))
    u, v = np.round(dist_uv[0, 0]).astype(int)
    image = np.zeros((480, 640), np.uint8)
    image[v - 3 : v + 4, u - 3 : u + 4] = 255
    out, out_cam = undistort_image(image, cam)
    assert out_cam.K == cam.K and out_cam.dist == () and out.shape == image.shape
    rows, cols = np.nonzero(out > 127)
    assert abs(cols.mean() - (400 + u - dist_uv[0, 0, 0])) < 1.0
    assert abs(rows.mean() - (300 + v - dist_uv[0, 0, 1])) < 1.0
    mask_out, _ = undistort_image(image > 127, cam, is_mask=True)
    assert mask_out.dtype == bool and mask_out.sum() > 0
    # no distortion: a copy and the same camera
    same, same_cam = undistort_image(image, make_camera())
    np.testing.assert_array_equal(same, image)
    assert same_cam == make_camera()
    with pytest.raises(ConfigError, match="camera is 640x480 but image is 64x48"):
        undistort_image(np.zeros((48, 64), np.uint8), cam)
