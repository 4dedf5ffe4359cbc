import cv2
import numpy as np
import pytest
import torch

from pipeline.errors import ConfigError, ShapeError
from pipeline.preprocess import (
    join_pieces,
    arc_length_keypoints,
    clean_mask,
    distance_to_mask,
    exact_distance_transform,
    foreground_window,
    keypoint_parameters,
    skeleton_path,
)

H, W = 240, 320


def band_mask(centerline_uv, half_width):
    """Flat-ended band of constant width around a (P, 2) pixel polyline (independent of the code under test)."""
    d = np.gradient(centerline_uv, axis=0)
    n = np.stack([-d[:, 1], d[:, 0]], 1) / np.linalg.norm(d, axis=1, keepdims=True)
    outline = np.concatenate([centerline_uv + half_width * n, (centerline_uv - half_width * n)[::-1]])
    mask = np.zeros((H, W), np.uint8)
    cv2.fillPoly(mask, [np.round(outline * 16).astype(np.int32)], 1, cv2.LINE_8, shift=4)
    return mask.astype(bool)


def arc(theta0=np.pi + 0.1, theta1=np.pi * 1.45, centre=(235.0, 250.0), radius=220.0, n=400):
    theta = np.linspace(theta0, theta1, n)
    return np.stack([centre[0] + radius * np.cos(theta), centre[1] + radius * np.sin(theta)], 1)


def distance_to_polyline(points, polyline):
    dense = np.concatenate([np.linspace(a, b, 20, endpoint=False) for a, b in zip(polyline[:-1], polyline[1:])])
    return np.linalg.norm(points[:, None] - dense[None], axis=2).min(axis=1)


def test_clean_mask_keeps_largest_and_fills_small_holes():
    mask = np.zeros((H, W), bool)
    mask[50:150, 50:200] = True
    mask[60:64, 60:64] = False  # 16 px hole: filled
    mask[100:120, 100:120] = False  # 400 px hole: kept
    mask[10:15, 250:255] = True  # small separate blob: dropped
    mask[0:30, 0:5] = True  # touches the border, separate: dropped
    out = clean_mask(mask, min_hole_px=64)
    expected = np.zeros((H, W), bool)
    expected[50:150, 50:200] = True
    expected[100:120, 100:120] = False
    np.testing.assert_array_equal(out, expected)
    assert not clean_mask(mask, min_hole_px=0)[60:64, 60:64].any()  # 0 fills nothing


def _clean_mask_reference(mask, min_hole_px):
    """clean_mask by scipy.ndimage over the whole image (independent of OpenCV and of the code's boxes): the largest
    8-connected component, then its 4-connected background regions that touch no image border and are small."""
    from scipy import ndimage

    labels, count = ndimage.label(mask, structure=np.ones((3, 3)))
    kept = labels == 1 + int(np.argmax(ndimage.sum(mask, labels, range(1, count + 1))))
    holes, count = ndimage.label(~kept)
    out = kept.copy()
    for label in range(1, count + 1):
        region = holes == label
        rows, cols = np.nonzero(region)
        inner = rows.min() > 0 and cols.min() > 0 and rows.max() < mask.shape[0] - 1 and cols.max() < mask.shape[1] - 1
        if inner and region.sum() < min_hole_px:
            out |= region
    return out


@pytest.mark.parametrize("seed", range(12))
def test_clean_mask_equals_a_whole_image_reference(seed):
    """Random blobs (several components, holes of all sizes, some open to the image border or to a gap between
    components, some touching the image's edges): ``clean_mask``, which works in the components' boxes, gives the
    whole-image reference's mask pixel for pixel."""
    rng = np.random.default_rng(seed)
    mask = np.zeros((60, 80), np.uint8)
    for _ in range(rng.integers(2, 6)):  # rings and discs, some cut by the image's edges
        centre = (int(rng.integers(-5, 85)), int(rng.integers(-5, 65)))
        cv2.circle(mask, centre, int(rng.integers(4, 25)), 1, int(rng.choice([-1, 2, 3, 5])))
    mask = mask.astype(bool) & (rng.random(mask.shape) > 0.03)  # pepper: small holes everywhere
    if not mask.any():
        mask[30, 40] = True
    for min_hole_px in (0, 5, 64, 10**6):
        np.testing.assert_array_equal(clean_mask(mask, min_hole_px=min_hole_px),
                                      _clean_mask_reference(mask, min_hole_px))


def test_clean_mask_does_not_fill_background_open_to_the_border():
    mask = np.zeros((H, W), bool)
    mask[:, 100:110] = True
    mask[0:10, :] = True
    out = clean_mask(mask, min_hole_px=10**6)
    np.testing.assert_array_equal(out, mask)


def test_errors():
    with pytest.raises(ShapeError, match="mask is empty"):
        clean_mask(np.zeros((H, W), bool))
    with pytest.raises(ShapeError, match="mask is empty"):
        skeleton_path(np.zeros((H, W), bool))
    with pytest.raises(ShapeError, match="bool"):
        skeleton_path(np.zeros((H, W), np.uint8))
    one = np.zeros((H, W), bool)
    one[5, 5] = True
    with pytest.raises(ShapeError, match="fewer than 2 pixels"):
        skeleton_path(one)
    with pytest.raises(ConfigError, match="min_hole_px"):
        clean_mask(one, min_hole_px=-1)
    with pytest.raises(ShapeError, match="mask is empty"):
        distance_to_mask(torch.zeros(H, W, dtype=torch.bool))
    with pytest.raises(ConfigError, match="'exact', 'kornia'"):
        distance_to_mask(torch.ones(H, W, dtype=torch.bool), method="scipy")


def test_skeleton_path_follows_a_thick_arc_base_at_border():
    truth = arc()  # base end 11 px from the bottom border, tip 33 px from the top
    mask = band_mask(truth, 12.0)
    path = skeleton_path(mask)
    assert path.shape[1] == 2 and path.dtype == np.float64
    assert distance_to_polyline(path, truth).max() < 2.0
    assert np.linalg.norm(path[-1] - truth[-1]) < 3.0  # tip reached (extended over the skeleton's shortfall)
    assert np.linalg.norm(path[0] - truth[0]) < 3.0
    short = skeleton_path(mask, extend_to_boundary=False)
    assert np.linalg.norm(short[-1] - truth[-1]) > 5.0  # the raw skeleton stops about a radius short


def test_skeleton_path_drops_spurs_and_uses_base_pixel():
    truth = np.stack([np.linspace(30, 250, 200), np.full(200, 120.0)], 1)
    mask = band_mask(truth, 10.0)
    mask[60:120, 150:158] = True  # a side branch towards the top
    path = skeleton_path(mask)
    assert distance_to_polyline(path, truth).max() < 2.0
    assert path[0, 0] < path[-1, 0]  # the left end is nearer the border (30 px against 69 px)
    assert np.linalg.norm(path[0] - truth[0]) < 3.0 and np.linalg.norm(path[-1] - truth[-1]) < 3.0
    flipped = skeleton_path(mask, base_pixel=(300.0, 120.0))
    np.testing.assert_allclose(flipped, path[::-1])


def test_arc_length_keypoints_on_straight_path():
    path = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 0.0], [40.0, 0.0]])
    points, s = arc_length_keypoints(path, k=4)
    np.testing.assert_allclose(s, [0.25, 0.5, 0.75, 1.0])
    np.testing.assert_allclose(points, [[10, 0], [20, 0], [30, 0], [40, 0]])
    points, s = arc_length_keypoints(path, k=4, include_tip=False)
    np.testing.assert_allclose(s, [0.2, 0.4, 0.6, 0.8])
    np.testing.assert_allclose(points[:, 0], [8, 16, 24, 32])
    np.testing.assert_allclose(keypoint_parameters(1), [1.0])
    with pytest.raises(ShapeError, match="zero length"):
        arc_length_keypoints(np.zeros((3, 2)))
    with pytest.raises(ConfigError, match="k: expected"):
        keypoint_parameters(0)


def test_keypoints_on_thick_arc_lie_on_centreline():
    truth = arc()
    points, _ = arc_length_keypoints(skeleton_path(band_mask(truth, 12.0)), k=4)
    expected, _ = arc_length_keypoints(truth, k=4)
    assert np.linalg.norm(points - expected, axis=1).max() < 3.0


def random_blobs(seed):
    rng = np.random.default_rng(seed)
    mask = np.zeros((60, 80), np.uint8)
    for _ in range(3):
        cv2.circle(mask, (int(rng.integers(0, 80)), int(rng.integers(0, 60))), int(rng.integers(2, 10)), 1, -1)
    return torch.from_numpy(mask.astype(bool))


def brute_force_distance(mask):
    m = mask.numpy()
    inside = np.argwhere(m)  # (P, 2) (row, col)
    grid = np.argwhere(np.ones_like(m))
    d = np.sqrt(((grid[:, None, :] - inside[None, :, :]) ** 2).sum(-1)).min(axis=1)
    return d.reshape(m.shape)


@pytest.mark.parametrize("seed", [0, 1])
def test_distance_exact_matches_brute_force_and_opencv(seed):
    mask = random_blobs(seed)
    d = distance_to_mask(mask)
    assert d.dtype == torch.float32 and d.shape == mask.shape
    assert (d[mask] == 0).all()
    # Exact: the brute-force minimum rounded to float32, bit for bit.
    np.testing.assert_array_equal(d.numpy(), brute_force_distance(mask).astype(np.float32))
    ref = cv2.distanceTransform((~mask.numpy()).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    np.testing.assert_allclose(d.numpy(), ref, atol=1e-5)
    np.testing.assert_allclose(distance_to_mask(mask.float()).numpy(), ref, atol=1e-5)


def test_exact_distance_transform_matches_brute_force_bit_for_bit():
    mask = random_blobs(3).numpy()
    expected = brute_force_distance(torch.from_numpy(mask))  # to the nearest True of mask = the nearest zero of ~mask
    for foreground in (~mask, (~mask).astype(np.uint8) * 7):
        d = exact_distance_transform(foreground)
        assert d.dtype == np.float64
        np.testing.assert_array_equal(d, expected)


@pytest.mark.parametrize("where", ["middle", "corner", "edge", "pixel"])
def test_exact_distance_transform_of_a_small_foreground_matches_brute_force(where):
    # The transform runs on the foreground's box grown by a pixel: the distances must be those of the whole image,
    # whether the box lies inside the image or is cut by its border (where no ring of zeros surrounds it).
    foreground = np.zeros((40, 50), bool)
    box = {"middle": (slice(12, 25), slice(20, 31)), "corner": (slice(0, 9), slice(38, 50)),
           "edge": (slice(15, 27), slice(0, 7)), "pixel": (slice(33, 34), slice(5, 6))}[where]
    foreground[box] = True
    if where != "pixel":
        foreground[box[0].start + 2, box[1].start + 3] = False  # a hole: a zero pixel inside the box
    expected = brute_force_distance(torch.from_numpy(~foreground))  # to the nearest zero of the foreground
    np.testing.assert_array_equal(exact_distance_transform(foreground), expected)


def test_foreground_window():
    mask = np.zeros((10, 12), bool)
    assert foreground_window(mask, 1) is None
    mask[3:5, 9] = True
    assert foreground_window(mask, 2) == (slice(1, 7), slice(7, 12))  # grown by 2, clipped at the right edge
    assert foreground_window(mask, 0) == (slice(3, 5), slice(9, 10))


def test_distance_does_not_depend_on_buffer_alignment():
    # OpenCV's DIST_MASK_PRECISE result changed in the last bits with the output buffer's alignment (on AVX2 / AVX-512
    # builds), which made pose fits of one input differ now and then; ours must be the same wherever the data lie.
    mask = random_blobs(4).numpy()
    outputs = []
    for offset in range(64):
        buffer = np.zeros(mask.size + 64, np.uint8)
        shifted = buffer[offset:offset + mask.size].view(bool).reshape(mask.shape)
        shifted[:] = mask
        outputs.append(distance_to_mask(torch.from_numpy(shifted)).numpy())
        outputs.append(exact_distance_transform(~shifted).astype(np.float32))
    for out in outputs[1:]:
        np.testing.assert_array_equal(out, outputs[0])


def test_exact_distance_transform_errors():
    with pytest.raises(ShapeError, match="no zero pixel"):
        exact_distance_transform(np.ones((4, 5), bool))
    with pytest.raises(ShapeError, match=r"\(H, W\)"):
        exact_distance_transform(np.ones((4, 5, 1), bool))
    np.testing.assert_array_equal(exact_distance_transform(np.zeros((2, 3), bool)), np.zeros((2, 3)))


def test_distance_kornia_is_an_approximation_within_documented_bound():
    mask = random_blobs(2)
    d = distance_to_mask(mask, method="kornia")
    ref = brute_force_distance(mask)
    assert d.dtype == torch.float32 and (d[mask] == 0).all()
    # Documented bound: never more than 1 px long, at most 35 % (+1 px) short (diagonals of the cascade), against
    # the brute force and against OpenCV's transform alike.
    opencv = cv2.distanceTransform((~mask.numpy()).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    for reference in (ref, opencv):
        assert (d.numpy() <= reference + 1.0).all()
        assert (d.numpy() >= 0.65 * reference - 1.0).all()


def _bar(H=80, W=200):
    """A horizontal bar of radius 8 px (rows 32-48, columns 20-179)."""
    mask = np.zeros((H, W), bool)
    mask[32:49, 20:180] = True
    return mask


def test_join_pieces_bridges_an_occluded_gap():
    whole = _bar()
    cut = whole.copy()
    cut[:, 95:111] = False  # an occluder 16 px wide (two radii) across the middle
    joined = join_pieces(cut)
    assert cv2.connectedComponents(joined.astype(np.uint8))[0] - 1 == 1
    assert (joined & whole).sum() / (joined | whole).sum() > 0.97
    assert (joined[cut]).all()  # nothing taken away


def test_join_pieces_leaves_other_masks_alone():
    whole = _bar()
    np.testing.assert_array_equal(join_pieces(whole), whole)
    speck = whole.copy()
    speck[5:8, 100:103] = True  # a small piece (below min_fraction of the bar's area) stays apart
    np.testing.assert_array_equal(join_pieces(speck), speck)
    far = _bar(W=400)
    far[32:49, 180:400] = False
    far[32:49, 300:390] = True  # a large piece 120 px away (15 radii) is not bridged
    np.testing.assert_array_equal(join_pieces(far), far)
    with pytest.raises(ShapeError):
        join_pieces(np.zeros((4, 4), bool))
