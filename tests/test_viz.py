"""Overlays and plots: drawn where they should be, inputs untouched, bad input named."""

import numpy as np
import pytest

from pipeline.errors import ShapeError
from pipeline.viz import draw_frames, draw_outline, draw_points, draw_polyline, plot_history


def test_outline_follows_the_silhouette_border():
    image = np.zeros((40, 50, 3), np.uint8)
    sil = np.zeros((40, 50))
    sil[10:30, 15:35] = 1
    out = draw_outline(image, sil, thickness=1)
    assert image.max() == 0  # input untouched
    drawn = out.any(axis=2)
    assert drawn[10, 20] and drawn[29, 20] and drawn[20, 15] and drawn[20, 34]
    assert not drawn[20, 25] and not drawn[2, 2]


def test_points_polyline_and_frames_land_at_their_pixels():
    image = np.zeros((40, 50, 3), np.uint8)
    assert draw_points(image, np.array([[10.0, 20.0]]), radius=2)[20, 10].any()
    assert draw_polyline(image, np.array([[5.0, 5.0], [45.0, 5.0]]), thickness=1)[5, 25].any()
    K = np.array([[50.0, 0, 25], [0, 50.0, 20], [0, 0, 1]])
    T = np.eye(4)
    T[:3, 3] = [0, 0, 1.0]
    out = draw_frames(image, T[None], K, axis_length_m=0.2, thickness=1)
    assert out[20, 30, 2] > 0  # x axis (red) points to +u
    assert out[25, 25, 1] > 0  # y axis (green) points to +v
    behind = T.copy()
    behind[2, 3] = -1.0
    assert draw_frames(image, behind[None], K).max() == 0


def _pure_red_pixels(image: np.ndarray) -> int:
    """Pixels that are red and nothing else (BGR): the white canvas, black text and grey curves are not."""
    b, g, r = (image[..., c].astype(int) for c in range(3))
    return int(((r > 200) & (g < 80) & (b < 80)).sum())


def test_history_plot_and_errors():
    """The best start's curve is the only red in the plot: there with ``best_start``, absent without it and when
    no loss is finite (nothing to draw)."""
    history = np.exp(-np.linspace(0, 5, 50))[:, None] * np.array([1.0, 2.0])
    img = plot_history(history, best_start=0)
    assert img.shape == (360, 560, 3)
    assert _pure_red_pixels(img) > 100  # a 2 px wide curve across the plot
    assert _pure_red_pixels(plot_history(history, best_start=None)) == 0
    assert _pure_red_pixels(plot_history(np.full((50, 2), np.nan), best_start=0)) == 0
    with pytest.raises(ShapeError, match="history"):
        plot_history(np.zeros((0, 2)))


def test_history_plot_with_labels_draws_each_curve_in_its_colour():
    history = np.exp(-np.linspace(0, 5, 50))[:, None] * np.array([1.0, 10.0])
    colors = [(0, 160, 0), (220, 120, 0)]
    img = plot_history(history, labels=["a", "b"], colors=colors, best_start=0)
    for color in colors:
        assert (img == color).all(axis=-1).sum() > 100  # a 2 px wide curve across the plot, and its legend line
    assert _pure_red_pixels(img) == 0
    with pytest.raises(ShapeError, match="one each per curve"):
        plot_history(history, labels=["a"], colors=colors[:1])
    with pytest.raises(ShapeError, match="one each per curve"):
        plot_history(history, labels=["a", "b"])
    with pytest.raises(ShapeError, match="image"):
        draw_outline(np.zeros((4, 4)), np.zeros((4, 4)))
