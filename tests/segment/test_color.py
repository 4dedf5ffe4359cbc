import pickle
from pathlib import Path

import cv2
import numpy as np
import pytest

from pipeline.errors import ConfigError, ShapeError
from pipeline.io import read_image, read_mask
from pipeline.segment import (
    COLOR_PRESETS,
    ColorSegmenter,
    ColorSegmenterConfig,
    color_preset,
    largest_component,
    make_segmenter,
    parse_hsv,
)
from pipeline.shapes.polyline import bezier_centerline
from pipeline.synth.soft_arm import random_bezier_arm, render_tube_image

DATA = Path(__file__).resolve().parents[2] / "data" / "soft_arm"


def iou(a, b):
    return (a & b).sum() / (a | b).sum()


def hsv_image(hsv_pixels):
    return cv2.cvtColor(np.asarray(hsv_pixels, np.uint8), cv2.COLOR_HSV2BGR)


@pytest.mark.parametrize("name", ["quadratic", "cubic_s", "pcc"])
def test_soft_arm_preset_on_bundled_examples(name):
    image = read_image(DATA / name / "image.png")
    truth = read_mask(DATA / name / "mask.png")
    mask = make_segmenter(color_preset("soft_arm"))(image)
    assert mask.dtype == bool and mask.shape == truth.shape
    assert iou(mask, truth) > 0.95


def test_soft_arm_preset_on_fresh_synthetic_images():
    H, W = 240, 320
    K = np.array([[260.0, 0.0, (W - 1) / 2], [0.0, 260.0, (H - 1) / 2], [0.0, 0.0, 1.0]])
    segmenter = ColorSegmenter(color_preset("soft_arm"))
    for seed in range(3):
        rng = np.random.default_rng(seed)
        centerline = bezier_centerline(random_bezier_arm(rng, K, (H, W), distance_m=0.45), 101)
        image, truth = render_tube_image(centerline, np.linspace(0.015, 0.008, 101), K, (H, W), rng)
        assert iou(segmenter(image), truth) > 0.9


def test_red_hue_range_wraps():
    # A disk whose left half has hue 175 and right half hue 4 (both red), on a green-blue background with specks.
    hsv = np.zeros((60, 80, 3), np.uint8)
    hsv[:] = (100, 200, 200)
    v, u = np.mgrid[0:60, 0:80]
    disk = (u - 40) ** 2 + (v - 30) ** 2 <= 20**2
    hsv[disk & (u < 40)] = (175, 220, 200)
    hsv[disk & (u >= 40)] = (4, 220, 200)
    hsv[5, 5] = (176, 220, 200)  # a red speck far from the disk
    image = hsv_image(hsv)
    wrap = ColorSegmenterConfig(hsv_lower=(170, 100, 50), hsv_upper=(10, 255, 255), open_px=0, close_px=0)
    assert wrap.hue_wraps
    mask = ColorSegmenter(wrap)(image)
    np.testing.assert_array_equal(mask, disk)  # both halves; the speck is not the largest component
    no_wrap = ColorSegmenterConfig(hsv_lower=(170, 100, 50), hsv_upper=(179, 255, 255), open_px=0, close_px=0)
    assert not no_wrap.hue_wraps
    np.testing.assert_array_equal(ColorSegmenter(no_wrap)(image), disk & (u < 40))
    everything = ColorSegmenterConfig(
        hsv_lower=(170, 100, 50), hsv_upper=(10, 255, 255), open_px=0, close_px=0, largest_component=False
    )
    assert ColorSegmenter(everything)(image).sum() == disk.sum() + 1


def test_morphology_opening_removes_specks_and_closing_fills_holes():
    hsv = np.zeros((50, 50, 3), np.uint8)
    hsv[:] = (60, 30, 100)  # dull green background
    hsv[10:40, 10:40] = (120, 200, 200)  # blue square
    hsv[25, 25] = (60, 30, 100)  # pinhole
    hsv[2, 45] = (120, 200, 200)  # speck
    image = hsv_image(hsv)
    square = np.zeros((50, 50), bool)
    square[10:40, 10:40] = True
    base = dict(hsv_lower=(110, 100, 50), hsv_upper=(130, 255, 255), largest_component=False)
    raw = ColorSegmenter(ColorSegmenterConfig(open_px=0, close_px=0, **base))(image)
    assert raw[2, 45] and not raw[25, 25]
    cleaned = ColorSegmenter(ColorSegmenterConfig(open_px=3, close_px=3, **base))(image)
    assert not cleaned[2, 45] and cleaned[25, 25]
    assert iou(cleaned, square) > 0.98


def test_largest_component():
    mask = np.zeros((10, 10), bool)
    mask[0:2, 0:2] = True
    mask[5:9, 5:9] = True
    out = largest_component(mask)
    assert out.sum() == 16 and out[5:9, 5:9].all()
    assert not largest_component(np.zeros((4, 4), bool)).any()


def test_config_validation_messages():
    with pytest.raises(ConfigError, match="hsv_lower: expected"):
        ColorSegmenterConfig(hsv_lower=(180, 0, 0), hsv_upper=(10, 255, 255))
    with pytest.raises(ConfigError, match="hsv_upper: expected"):
        ColorSegmenterConfig(hsv_lower=(0, 0, 0), hsv_upper=(10, 255))
    with pytest.raises(ConfigError, match="saturation lower bound 200 is above its upper bound 100"):
        ColorSegmenterConfig(hsv_lower=(0, 200, 0), hsv_upper=(10, 100, 255))
    with pytest.raises(ConfigError, match="open_px: expected an int >= 0"):
        ColorSegmenterConfig(hsv_lower=(0, 0, 0), hsv_upper=(10, 255, 255), open_px=-1)
    with pytest.raises(ConfigError, match="unknown colour preset 'purple'; presets: soft_arm, red"):
        color_preset("purple")
    with pytest.raises(ConfigError, match="--hsv-lower: expected H,S,V"):
        parse_hsv("1,2", "--hsv-lower")
    assert parse_hsv("170, 100,50", "x") == (170, 100, 50)
    assert set(COLOR_PRESETS) >= {"soft_arm", "red", "green", "blue"}


def test_bad_image_and_pickling():
    segmenter = ColorSegmenter(color_preset("red"))
    with pytest.raises(ShapeError, match=r"expected an \(H, W, 3\) uint8 BGR array, got float64"):
        segmenter(np.zeros((4, 4, 3)))
    with pytest.raises(ShapeError, match="frame_index: expected an int >= 0"):
        segmenter(np.zeros((4, 4, 3), np.uint8), frame_index=-1)
    again = pickle.loads(pickle.dumps(segmenter))
    assert again.config == segmenter.config
