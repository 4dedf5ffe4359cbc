"""Auto segmenter (network mask refined by GrabCut): arms of colours no preset knows, rims put back, errors."""

import pickle

import cv2
import numpy as np
import pytest

from pipeline.errors import ConfigError, ShapeError
from pipeline.segment import (AutoSegmenter, AutoSegmenterConfig, color_preset, grabcut_refine, make_segmenter,
                              refine_components)
from pipeline.shapes.polyline import bezier_centerline
from pipeline.synth.soft_arm import random_bezier_arm, render_tube_image

H, W = 360, 640
K = np.array([[350.0, 0.0, (W - 1) / 2], [0.0, 350.0, (H - 1) / 2], [0.0, 0.0, 1.0]])
#: Arm colours outside every colour preset's hue range: purple, teal, olive (BGR).
UNSEEN = [(150, 40, 120), (140, 130, 20), (40, 120, 110)]


def arm_image(seed, colour):
    """A random arm drawn area-averaged (``supersample=4``, a camera's rim) over clutter, and its exact mask."""
    rng = np.random.default_rng(seed)
    centerline = bezier_centerline(random_bezier_arm(rng, K, (H, W), distance_m=0.4, order=2 + seed % 2), 101)
    return render_tube_image(centerline, np.linspace(0.014, 0.006, 101), K, (H, W), rng, arm_color_bgr=colour,
                             supersample=4)


def iou(a, b):
    return (a & b).sum() / (a | b).sum()


@pytest.fixture(scope="module")
def auto():
    return make_segmenter(AutoSegmenterConfig(device="cpu", num_threads=1))


def test_unseen_arm_colours_are_segmented_with_their_true_area(auto):
    # The former default (the soft_arm colour preset) finds nothing of these arms; the auto segmenter finds each
    # with IoU > 0.95 and its area within 3 % of the exact mask's (measured: IoU 0.98-0.99, area 0.99-1.01).
    for seed, colour in enumerate(UNSEEN):
        image, truth = arm_image(seed, colour)
        preset = make_segmenter(color_preset("soft_arm"))(image)
        assert iou(preset, truth) < 0.2
        mask = auto(image)
        assert mask.shape == truth.shape and mask.dtype == bool
        assert iou(mask, truth) > 0.95, (seed, iou(mask, truth))
        assert abs(mask.sum() / truth.sum() - 1.0) < 0.03, (seed, mask.sum() / truth.sum())


@pytest.mark.parametrize("operation", [cv2.erode, cv2.dilate])
def test_grabcut_moves_a_wrong_rim_back(operation):
    # A first mask 3 px too narrow or too wide (no network involved; area off by 30-45 % on this thin arm) comes
    # back to within 5 % of the true area (measured on 4 arms: -2.4 % to -0.3 % from narrow, +2.3 % to +4.3 % from
    # wide: about a quarter of a pixel of rim, depending on the start). From a rim this far off GrabCut needs 5
    # iterations to converge from every k-means seed: at the default 3, seeds 1-7 give this arm IoU 0.98 from the
    # narrow start and seed 0 0.87 (the network's first masks converge in 3: docs/segmenters.md).
    image, truth = arm_image(3, UNSEEN[1])
    first = operation(truth.astype(np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (7, 7))) > 0
    assert abs(first.sum() / truth.sum() - 1.0) > 0.25
    refined = grabcut_refine(image, first, band_px=6, iterations=5)
    assert iou(refined, truth) > 0.94
    assert abs(refined.sum() / truth.sum() - 1.0) < 0.05, refined.sum() / truth.sum()


def test_every_large_component_is_refined_on_its_own():
    """``refine_components`` (the auto segmenter with every component kept): the arm's refined mask is the one it
    gets alone, whatever else the first mask holds (a clutter blob far off, a speck: refined in one crop with the
    arm, they would move its colour models and widen the crop); the speck (under ``REFINE_COMPONENT_FRACTION``)
    is kept as it is."""
    image, truth = arm_image(3, UNSEEN[1])
    first = cv2.erode(truth.astype(np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (5, 5))) > 0
    blob, speck = np.zeros((H, W), np.uint8), np.zeros((H, W), bool)
    far = cv2.distanceTransform(1 - cv2.dilate(truth.astype(np.uint8), np.ones((60, 60), np.uint8)), cv2.DIST_L2, 5)
    far[:50], far[-50:], far[:, :80], far[:, -80:] = 0, 0, 0, 0
    v, u = np.unravel_index(int(np.argmax(far)), far.shape)
    cv2.ellipse(blob, (int(u), int(v)), (70, 35), 10, 0, 360, 1, -1)
    speck[5:8, 5:8] = True
    every = first | blob.astype(bool) | speck
    assert not (blob.astype(bool) & truth).any()
    refined = refine_components(image, every, band_px=6, iterations=3)
    alone = grabcut_refine(image, first, band_px=6, iterations=3)
    np.testing.assert_array_equal(refined & truth_region(truth), alone & truth_region(truth))
    assert refined[5:8, 5:8].all() and refined.sum() > alone.sum() + 0.5 * blob.sum()
    together = grabcut_refine(image, every, band_px=6, iterations=3)  # one crop for all: the arm's rim moves
    assert (together & truth_region(truth) != alone & truth_region(truth)).any()


def truth_region(truth):
    """The pixels within 20 px of the exact mask (where the arm's refinement may put its rim)."""
    return cv2.dilate(truth.astype(np.uint8), np.ones((41, 41), np.uint8)) > 0


def test_a_frame_s_mask_depends_on_the_image_alone():
    # GrabCut draws from OpenCV's random generator of the calling thread: the same image and first mask must give
    # the same mask whatever ran before (the generator moved on by other draws) and in another thread.
    import threading

    image, truth = arm_image(5, UNSEEN[0])
    image = cv2.imdecode(cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 80])[1], cv2.IMREAD_COLOR)
    first = cv2.dilate(truth.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    masks = []
    for _ in range(3):
        cv2.randu(np.empty((50, 50)), 0.0, 1.0)  # other use of the generator in between
        masks.append(grabcut_refine(image, first))
    thread = threading.Thread(target=lambda: masks.append(grabcut_refine(image, first)))
    thread.start()
    thread.join()
    assert all(np.array_equal(mask, masks[0]) for mask in masks[1:])
    assert iou(masks[0], truth) > 0.9


def test_empty_first_mask_stays_empty_and_bad_inputs_raise():
    image = np.zeros((40, 50, 3), np.uint8)
    assert not grabcut_refine(image, np.zeros((40, 50), bool)).any()
    with pytest.raises(ShapeError, match=r"first_mask: expected an \(40, 50\) bool array"):
        grabcut_refine(image, np.zeros((40, 49), bool))
    with pytest.raises(ConfigError, match="band_px: expected an int >= 1"):
        grabcut_refine(image, np.zeros((40, 50), bool), band_px=0)
    with pytest.raises(ConfigError, match="iterations: expected an int >= 1"):
        AutoSegmenterConfig(iterations=0)
    with pytest.raises(ConfigError, match="config: expected an AutoSegmenterConfig"):
        AutoSegmenter(color_preset("red"))


def test_whole_image_mask_is_returned_unrefined():
    image = np.random.default_rng(0).integers(0, 255, (30, 40, 3), dtype=np.uint8)
    full = np.ones((30, 40), bool)
    np.testing.assert_array_equal(grabcut_refine(image, full), full)


def test_pickling_rebuilds_the_network(auto):
    again = pickle.loads(pickle.dumps(auto))
    assert isinstance(again, AutoSegmenter) and again.config == auto.config
