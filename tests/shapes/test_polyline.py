import numpy as np
import pytest

from pipeline.errors import ConfigError, ShapeError
from pipeline.shapes.polyline import bezier_centerline, points_at_arc_length, polyline_arc_length, resample_polyline


def test_resample_uniform_spacing_on_l_shape():
    pts = np.array([[0.0, 0.0], [3.0, 0.0], [3.0, 1.0]])
    out = resample_polyline(pts, 5)  # total 4: points every 1.0
    np.testing.assert_allclose(out, [[0, 0], [1, 0], [2, 0], [3, 0], [3, 1]])


def test_resample_keeps_ends_and_handles_duplicates():
    pts = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [1.0, 1.0, 1.0], [2.0, 2.0, 2.0]])
    out = resample_polyline(pts, 3)
    np.testing.assert_allclose(out, [[0, 0, 0], [1, 1, 1], [2, 2, 2]])
    np.testing.assert_allclose(resample_polyline(np.ones((3, 2)), 4), np.ones((4, 2)))


def test_points_at_arc_length_interpolates_and_clamps():
    pts = np.array([[0.0, 0.0], [3.0, 0.0], [3.0, 0.0], [3.0, 1.0]])  # length 4, a repeated corner
    out = points_at_arc_length(pts, np.array([-1.0, 0.5, 3.0, 3.25, 4.0, 9.0]))
    np.testing.assert_allclose(out, [[0, 0], [0.5, 0], [3, 0], [3, 0.25], [3, 1], [3, 1]], atol=1e-15)
    with pytest.raises(ShapeError, match=r"\(N, D\)"):
        points_at_arc_length(np.zeros(3), np.array([0.0]))


def test_arc_length():
    np.testing.assert_allclose(polyline_arc_length(np.array([[0.0, 0.0], [3.0, 4.0], [3.0, 5.0]])), [0, 5, 6])


def test_bezier_centerline_is_uniform_in_arc_length():
    cp = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [1.0, 1.0, 1.0]])
    c = bezier_centerline(cp, 11)
    np.testing.assert_allclose(c[[0, -1]], cp[[0, -1]])
    # Independent reference: a very dense sampling of the parabola, its cumulative length at the nearest sample.
    t = np.linspace(0, 1, 200001)[:, None]
    dense = (1 - t) ** 2 * cp[0] + 2 * t * (1 - t) * cp[1] + t**2 * cp[2]
    cumulative = polyline_arc_length(dense)
    nearest = np.argmin(np.linalg.norm(dense[None] - c[:, None], axis=2), axis=1)
    np.testing.assert_allclose(cumulative[nearest], np.linspace(0, cumulative[-1], 11), atol=2e-5)


def test_errors():
    with pytest.raises(ShapeError, match=r"\(N, D\)"):
        resample_polyline(np.zeros(3), 4)
    with pytest.raises(ConfigError, match="n: expected"):
        resample_polyline(np.zeros((3, 2)), 1)
    with pytest.raises(ShapeError, match="NaN"):
        resample_polyline(np.array([[0.0, np.nan]]), 4)
