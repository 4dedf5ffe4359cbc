"""``image_rim_offset_px``: a mask's rim bias read from the image's edges, against the area a disc adds or takes
away (analytic) and against ``pipeline.evaluate.rim_offset_px`` on a tube drawn by the synthetic renderer."""

import math

import cv2
import numpy as np
import pytest

from pipeline.errors import ShapeError
from pipeline.evaluate import rim_offset_px
from pipeline.segment import image_rim_offset_px
from pipeline.shapes.polyline import bezier_centerline
from pipeline.synth.soft_arm import random_bezier_arm, render_tube_image

H, W = 120, 160
CENTRE = (80.3, 59.6)  # (x, y), off the pixel grid
RADIUS = 30.4


def _disc_image(shaded: bool, supersample: int = 16) -> np.ndarray:
    """A disc on a two-colour background, each pixel the average over ``supersample``^2 points of its area (a
    camera's pixel); ``shaded``: the disc's colour falls towards its rim, as a lit sphere's (the steepest change
    next to the edge)."""
    offsets = (np.arange(supersample) + 0.5) / supersample - 0.5
    ys = np.arange(H)[:, None, None, None] + offsets[None, None, :, None]
    xs = np.arange(W)[None, :, None, None] + offsets[None, None, None, :]
    r = np.hypot(xs - CENTRE[0], ys - CENTRE[1])  # (H, W, s, s)
    inside = r < RADIUS
    light = np.sqrt(np.clip(1.0 - (r / RADIUS) ** 2, 0.0, 1.0)) if shaded else np.ones_like(r)
    arm = np.array([40.0, 90.0, 200.0])[None, None, None, None] * (0.45 + 0.55 * light[..., None])
    background = np.where((xs < 70)[..., None], [60.0, 160.0, 70.0], [150.0, 120.0, 40.0])
    colour = np.where(inside[..., None], arm, background).mean(axis=(2, 3))
    return np.clip(np.round(colour), 0, 255).astype(np.uint8)


def _disc_mask(radius: float) -> np.ndarray:
    """Pixels whose centre lies within ``radius`` of the disc's centre: a mask whose rim lies about ``radius -
    RADIUS`` outside the true disc's."""
    y, x = np.mgrid[0:H, 0:W]
    return np.hypot(x - CENTRE[0], y - CENTRE[1]) < radius


@pytest.mark.parametrize("shaded", [False, True])
@pytest.mark.parametrize("grow", [-1.3, -0.4, 0.0, 0.25, 0.8, 1.5])
def test_a_disc_masks_rim_offset_is_the_area_it_adds_over_the_true_outline(shaded, grow):
    """Against the analytic offset ``(mask area - pi R^2) / (2 pi R)``: within 0.12 px, flat or shaded, masks too
    narrow and too wide by up to 1.5 px."""
    mask = _disc_mask(RADIUS + grow)
    expected = (mask.sum() - math.pi * RADIUS**2) / (2 * math.pi * RADIUS)
    assert image_rim_offset_px(_disc_image(shaded), mask) == pytest.approx(expected, abs=0.12)


def _tube(seed: int, f: float = 500.0) -> tuple[np.ndarray, np.ndarray]:
    """The synthetic soft arm at 640x480 (area-averaged rim pixels, clutter, blur and noise), 0.3 m away: its image
    and exact mask (about 33 px wide on average at ``f`` 500 px)."""
    K = np.array([[f, 0.0, 319.5], [0.0, f, 239.5], [0.0, 0.0, 1.0]])
    rng = np.random.default_rng(seed)
    truth = bezier_centerline(random_bezier_arm(rng, K, (480, 640), length_m=0.2, distance_m=0.3, order=2), 201)
    return render_tube_image(truth, np.linspace(0.014, 0.006, 201), K, (480, 640), rng, supersample=4)


def test_a_tube_drawn_by_the_renderer_reads_its_exact_mask_as_exact_and_a_dilated_one_as_wide():
    """The exact mask reads within 0.1 px of 0; dilated or eroded by a 3 x 3 square, within 0.2 px of the area the
    mask adds or takes away (``pipeline.evaluate.rim_offset_px``, about +-1.2 px)."""
    for seed in (3, 4):
        image, mask = _tube(seed)
        assert abs(image_rim_offset_px(image, mask)) < 0.1
        square = np.ones((3, 3), np.uint8)
        for changed in (cv2.dilate(mask.astype(np.uint8), square) > 0, cv2.erode(mask.astype(np.uint8), square) > 0):
            reference = rim_offset_px(changed, mask)
            assert 0.9 < abs(reference) < 1.6
            assert image_rim_offset_px(image, changed) == pytest.approx(reference, abs=0.2)


def test_a_narrow_arm_reads_nothing():
    """The same arm a third as wide in pixels (``f`` 170 px: about 11 px, under ``MIN_WIDTH_PX``), its mask dilated:
    0.0, where at 500 px the same dilation reads about +1.2."""
    from pipeline.segment.rim import MIN_WIDTH_PX

    square = np.ones((3, 3), np.uint8)
    for f, readable in ((170.0, False), (500.0, True)):
        image, mask = _tube(3, f)
        outline = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)[0][0]
        width = 2 * mask.sum() / cv2.arcLength(outline, True)  # the mean width, as the function measures it
        assert (width >= MIN_WIDTH_PX) == readable, width
        reading = image_rim_offset_px(image, cv2.dilate(mask.astype(np.uint8), square) > 0)
        assert reading > 0.9 if readable else reading == 0.0


def test_an_outline_without_contrast_reads_nothing_and_bad_masks_are_named():
    """A mask on a flat image (no edge to read): 0.0, not NaN; too few outline pixels: 0.0; a mask that is not a
    bool array of the image's size, or is empty, raises ``ShapeError`` naming it."""
    flat = np.full((H, W, 3), 128, np.uint8)
    assert image_rim_offset_px(flat, _disc_mask(RADIUS)) == 0.0
    speck = np.zeros((H, W), bool)
    speck[50, 50] = True
    assert image_rim_offset_px(_disc_image(False), speck) == 0.0
    with pytest.raises(ShapeError, match=r"mask: expected an \(120, 160\) bool array"):
        image_rim_offset_px(flat, _disc_mask(RADIUS).astype(np.uint8))
    with pytest.raises(ShapeError, match=r"mask: expected an \(120, 160\) bool array"):
        image_rim_offset_px(flat, np.ones((H, W + 1), bool))
    with pytest.raises(ShapeError, match="mask: empty"):
        image_rim_offset_px(flat, np.zeros((H, W), bool))
