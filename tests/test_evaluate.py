import numpy as np
import pytest

from pipeline.errors import ConfigError, ShapeError
from pipeline.evaluate import centerline_errors, mask_iou, rim_offset_px
from pipeline.shapes.polyline import bezier_centerline

K = np.array([[600.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])
CP = np.array([[-0.05, 0.02, 0.4], [0.03, 0.0, 0.45], [0.08, 0.06, 0.42]])


def test_identical_is_zero_and_keys():
    c = bezier_centerline(CP, 101)
    e = centerline_errors(c, c, K)
    assert set(e) == {
        "mean_2d_px", "median_2d_px", "max_2d_px", "tip_2d_px",
        "mean_3d_mm", "median_3d_mm", "max_3d_mm", "tip_3d_mm", "length_error_mm", "n_samples",
    }  # fmt: skip
    assert all(abs(v) < 1e-9 for k, v in e.items() if k != "n_samples") and e["n_samples"] == 101


def test_translation_matches_naive_loop():
    truth = bezier_centerline(CP, 101)
    shift = np.array([0.01, -0.002, 0.0])
    e = centerline_errors(truth + shift, truth, K)
    assert e["mean_3d_mm"] == pytest.approx(np.linalg.norm(shift) * 1000)
    assert e["length_error_mm"] == pytest.approx(0.0, abs=1e-9)
    expected = []
    for p in truth:  # naive pinhole, one point at a time
        a = (K[0, 0] * p[0] / p[2] + K[0, 2], K[1, 1] * p[1] / p[2] + K[1, 2])
        q = p + shift
        b = (K[0, 0] * q[0] / q[2] + K[0, 2], K[1, 1] * q[1] / q[2] + K[1, 2])
        expected.append(np.hypot(a[0] - b[0], a[1] - b[1]))
    assert e["mean_2d_px"] == pytest.approx(np.mean(expected))
    assert e["max_2d_px"] == pytest.approx(np.max(expected))
    assert e["tip_2d_px"] == pytest.approx(expected[-1])


def test_independent_of_input_sampling():
    dense = bezier_centerline(CP, 1001)
    s = np.linspace(0, 1, 2001)[:, None]  # uniform in the Bezier parameter, not in arc length
    uneven = (1 - s) ** 2 * CP[0] + 2 * s * (1 - s) * CP[1] + s**2 * CP[2]
    e = centerline_errors(uneven, dense, K, n_samples=51)
    assert e["mean_3d_mm"] < 1e-3 and e["mean_2d_px"] < 1e-2 and e["n_samples"] == 51


def test_order_matters():
    c = bezier_centerline(CP, 101)
    assert centerline_errors(c[::-1], c, K)["mean_3d_mm"] > 10


def test_errors():
    c = bezier_centerline(CP, 11)
    with pytest.raises(ShapeError, match="est_points_cam"):
        centerline_errors(c[:, :2], c, K)
    with pytest.raises(ShapeError, match="behind the camera"):
        centerline_errors(c * [1, 1, -1], c, K)
    with pytest.raises(ConfigError, match="n_samples"):
        centerline_errors(c, c, K, n_samples=1)
    with pytest.raises(ShapeError, match="K"):
        centerline_errors(c, c, np.eye(2))


def test_mask_iou_against_counting_and_errors():
    rng = np.random.default_rng(0)
    a, b = rng.random((20, 30)) > 0.5, rng.random((20, 30)) > 0.3
    both = sum(1 for i in range(20) for j in range(30) if a[i, j] and b[i, j])
    either = sum(1 for i in range(20) for j in range(30) if a[i, j] or b[i, j])
    assert mask_iou(a, b) == pytest.approx(both / either)
    empty = np.zeros((4, 4), bool)
    assert mask_iou(empty, empty) == 1.0 and mask_iou(a, a) == 1.0
    with pytest.raises(ShapeError, match="differ in size"):
        mask_iou(a, b[:10])
    with pytest.raises(ShapeError, match="bool"):
        mask_iou(a.astype(np.uint8), b)


def _disc(radius, size=201):
    v, u = np.mgrid[:size, :size]
    return (u - 100.0) ** 2 + (v - 100.0) ** 2 <= radius**2


@pytest.mark.parametrize("grown", [1.0, -1.0, 2.0, -2.0])
def test_rim_offset_of_a_grown_disc_is_how_far_it_grew(grown):
    """Digital discs of radius R + d against those of radius R: the outline moved by d. Concentric circles' area
    difference over the inner circumference is d (1 + d / 2R); a digital disc's pixel count is off that by up to
    11 % of d at R = 20, so the ratio is averaged over radii 20-40 px (lattice noise, not the function's)."""
    radii = np.arange(20.0, 40.0, 0.7)
    ratios = [rim_offset_px(_disc(r + grown), _disc(r)) / (grown * (1 + grown / (2 * r))) for r in radii]
    assert np.mean(ratios) == pytest.approx(1.0, abs=0.03) and min(ratios) > 0.85, ratios
    assert rim_offset_px(_disc(30.0), _disc(30.0)) == 0.0


def test_rim_offset_counts_holes_in_the_outline():
    """A ring (a disc with a hole) dilated by one pixel grows on both of its outlines."""
    ring, grown = _disc(40.0) & ~_disc(20.0), _disc(41.0) & ~_disc(19.0)
    assert rim_offset_px(grown, ring) == pytest.approx(1.0, abs=0.1)


def test_rim_offset_errors_name_the_problem():
    with pytest.raises(ShapeError, match="the true mask is empty"):
        rim_offset_px(_disc(5.0), np.zeros((201, 201), bool))
    with pytest.raises(ShapeError, match="differ in size"):
        rim_offset_px(_disc(5.0), _disc(5.0, size=150))
