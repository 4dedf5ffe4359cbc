"""A mask's rim bias read from the image it was segmented from: how far its outline lies outside the image's edges.

A soft arm's depth is read from its apparent width, so a segmenter whose outline lies 0.2-0.4 px outside (or
inside) the arm's costs about 5-10 mm of depth on the project's 1280x720 arms (``docs/soft-arms.md``). The image
itself says where the arm's edge is, to a fraction of a pixel: a camera's pixel on the edge averages arm and
background by the area each covers, so along the outline's normal the colour steps from the arm's to the
background's over about one pixel, and the centroid of that step's colour change is the edge. The mask's own
outline, sampled along the same normals, steps where the mask ends; the mean difference is the mask's rim offset,
as ``ShapeFitConfig.rim_offset_px`` takes it (``rim_offset_px="image"``).

Per profile (one per outline pixel of OpenCV's contours, holes' included): the image and the mask sampled along
the outward normal (the gradient of the mask smoothed by a Gaussian of ``NORMAL_SIGMA_PX``) every ``STEP_PX`` from
``-REACH_PX`` to ``REACH_PX + 1`` px around the outline pixel (OpenCV's bilinear ``remap``), the colour change
between samples (its Euclidean norm over the channels), and the centroid of the change within ``WINDOW_PX`` of its
largest, less the straight line through the change just outside that window (a shading's slow change, which would
pull the centroid its way). A profile counts where its largest change over one step is at least ``MIN_CONTRAST`` grey levels (arm
and background of about the same colour, the image's border), not at the ends of the profile (an edge farther
than ``REACH_PX``), and where the colour a pixel beyond the edge is the background's (``BACKGROUND_MATCH``: a rim
shaded dark against a dark background changes most inside the arm). The offsets of the profiles that count, the
``TRIM`` fraction at either end dropped, are averaged.
"""

from __future__ import annotations

import cv2
import numpy as np

from pipeline.errors import ShapeError
from pipeline.preprocess import outline_length
from pipeline.segment.base import check_bgr_image

#: Sample spacing along a profile, pixels.
STEP_PX = 0.5
#: Profiles reach this far inside and this far plus one pixel outside the outline pixel's centre, pixels.
REACH_PX = 3.0
#: The centroid of a profile's colour change is taken within this distance of its largest change, pixels.
WINDOW_PX = 1.0
#: A profile counts when its largest colour change over one ``STEP_PX`` is at least this (0-255 per channel).
MIN_CONTRAST = 12.0
#: The fraction of the profiles' offsets dropped at either end before averaging (clutter edges, a wrong edge).
TRIM = 0.1
#: The Gaussian that smooths the mask for its outline's normals, pixels.
NORMAL_SIGMA_PX = 2.0
#: A profile counts only where the colour a pixel beyond its edge differs from the colour at its outer end by at
#: most this fraction of the edge's step (one pixel either side of it): beyond an edge lies the background.
BACKGROUND_MATCH = 0.35
#: Fewer profiles than this that count: nothing is measured (offset 0).
MIN_PROFILES = 20
#: A mask narrower than this on average (twice its area over its outline's length), pixels: nothing is measured
#: (offset 0). On arms 10-25 px wide (the 1280x720 tuning images halved, then JPEG-compressed) the readings were no
#: closer to the masks' true offsets than 0 is (why is not traced); on 21-49 px (1280x720) 0.05 px rms off.
MIN_WIDTH_PX = 24.0


def image_rim_offset_px(image: np.ndarray, mask: np.ndarray) -> float:
    """How far ``mask``'s outline lies outside the edges of the object in ``image``, pixels (see the module).

    Args:
        image: ``(H, W, 3)`` uint8 BGR, the image ``mask`` was segmented from.
        mask: ``(H, W)`` bool, the object's mask (one or several components).

    Returns:
        The mean offset, pixels: positive where the mask is too wide, negative too narrow; 0.0 when fewer than
        ``MIN_PROFILES`` profiles of the outline have enough contrast (nothing to read the edge from), or when the
        mask is narrower than ``MIN_WIDTH_PX`` on average.

    Raises:
        ShapeError: ``mask`` is not an ``(H, W)`` bool array of the image's size, or is empty.
    """
    H, W = check_bgr_image(image)
    if not isinstance(mask, np.ndarray) or mask.shape != (H, W) or mask.dtype != bool:
        got = f"{mask.dtype} {mask.shape}" if isinstance(mask, np.ndarray) else type(mask).__name__
        raise ShapeError(f"mask: expected an ({H}, {W}) bool array (the image's size), got {got}")
    if not mask.any():
        raise ShapeError("mask: empty (no outline to measure)")
    rows, cols = np.nonzero(mask)
    margin = int(REACH_PX) + 3 * int(np.ceil(NORMAL_SIGMA_PX)) + 2
    y0, y1 = max(int(rows.min()) - margin, 0), min(int(rows.max()) + margin + 1, H)
    x0, x1 = max(int(cols.min()) - margin, 0), min(int(cols.max()) + margin + 1, W)
    crop = np.ascontiguousarray(image[y0:y1, x0:x1], dtype=np.float32)
    inside = mask[y0:y1, x0:x1].astype(np.float32)
    points, normals, length = _outline_normals(inside)
    if len(points) < MIN_PROFILES or 2.0 * float(inside.sum()) / max(length, 1.0) < MIN_WIDTH_PX:
        return 0.0
    t = np.arange(-REACH_PX, REACH_PX + 1.0 + 1e-6, STEP_PX, dtype=np.float32)  # (T,)
    map_x = np.ascontiguousarray(points[:, :1] + normals[:, :1] * t[None], dtype=np.float32)  # (N, T)
    map_y = np.ascontiguousarray(points[:, 1:] + normals[:, 1:] * t[None], dtype=np.float32)
    colour = cv2.remap(crop, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)  # (N, T, 3)
    level = cv2.remap(inside, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)  # (N, T)
    change = np.linalg.norm(np.diff(colour, axis=1), axis=-1)  # (N, T-1), per step
    mask_change = np.abs(np.diff(level, axis=1))
    middle = 0.5 * (t[1:] + t[:-1])  # (T-1,) where each change is
    edge, largest, peak = _step_centroid(change, middle)
    mask_edge, _, _ = _step_centroid(mask_change, middle)
    counts = (peak >= MIN_CONTRAST) & (largest > 0) & (largest < len(middle) - 1)
    # Beyond an edge lies the background: where the colour a pixel past the change still differs from the profile's
    # outer end, the change was the arm's own shading (a dark rim on a dark background), not its edge.
    rows = np.arange(len(colour))
    beyond = np.clip(np.searchsorted(t, edge + 1.0), 0, len(t) - 1)
    before = np.clip(np.searchsorted(t, edge - 1.0) - 1, 0, len(t) - 1)
    step = np.linalg.norm(colour[rows, before] - colour[rows, beyond], axis=-1)
    rest = np.linalg.norm(colour[rows, beyond] - colour[:, -1], axis=-1)
    counts &= rest <= BACKGROUND_MATCH * step
    offsets = np.sort(mask_edge[counts] - edge[counts])
    if len(offsets) < MIN_PROFILES:
        return 0.0
    drop = int(TRIM * len(offsets))
    return float(offsets[drop:len(offsets) - drop].mean())


def _outline_normals(inside: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """``(N, 2)`` outline pixels ``(x, y)`` of a ``(h, w)`` float 0/1 mask (OpenCV contours, holes' included),
    their ``(N, 2)`` unit outward normals (the smoothed mask's falling gradient; pixels where it is flat dropped) and
    the outline's length, pixels (``pipeline.preprocess.outline_length``, as ``pipeline.evaluate.rim_offset_px``
    measures it)."""
    contours, _ = cv2.findContours(inside.astype(np.uint8), cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
    length = outline_length(contours)
    points = np.concatenate([c.reshape(-1, 2) for c in contours]).astype(np.float32)
    smooth = cv2.GaussianBlur(inside, (0, 0), NORMAL_SIGMA_PX)
    grad_y, grad_x = np.gradient(smooth)
    x, y = points[:, 0].astype(int), points[:, 1].astype(int)
    normals = -np.stack([grad_x[y, x], grad_y[y, x]], axis=1)
    norm = np.linalg.norm(normals, axis=1)
    keep = norm > 1e-3
    return points[keep], normals[keep] / norm[keep, None], length


def _step_centroid(change: np.ndarray, middle: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per profile of ``change`` ``(N, T-1)`` at positions ``middle`` ``(T-1,)`` (every ``STEP_PX``): the centroid
    of the change within ``WINDOW_PX`` of its largest, less the straight line through the change just outside that
    window on either side (a shading's slow change, which would pull the centroid its way), ``(N,)``; the largest's
    index ``(N,)`` and value ``(N,)``."""
    rows, count = np.arange(len(change)), change.shape[1]
    largest = np.argmax(change, axis=1)
    reach = int(round(WINDOW_PX / STEP_PX)) + 1
    low, high = np.clip(largest - reach, 0, count - 1), np.clip(largest + reach, 0, count - 1)
    fraction = (np.arange(count)[None] - low[:, None]) / np.maximum(high - low, 1)[:, None]
    line = change[rows, low][:, None] + (change[rows, high] - change[rows, low])[:, None] * fraction
    window = np.abs(middle[None] - middle[largest][:, None]) <= WINDOW_PX + 1e-6
    weight = np.where(window, np.clip(change - line, 0.0, None), 0.0)
    centroid = (weight * middle[None]).sum(axis=1) / np.maximum(weight.sum(axis=1), 1e-12)
    return centroid, largest, change[rows, largest]
