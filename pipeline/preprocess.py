"""From a binary robot mask to what the losses need: a cleaned mask, a distance map, a skeleton path, keypoints.

Convention: masks here are ``(H, W)`` bool numpy arrays (as ``pipeline.io.read_mask`` returns them), except
``distance_to_mask``, which takes and returns torch tensors for the losses. Pixels are ``(u, v)`` = (column, row)
with pixel centres at integer coordinates (as in ``pipeline.camera``).
"""

from __future__ import annotations

import cv2
import numpy as np
import torch
from scipy.ndimage import distance_transform_edt
from scipy.sparse.csgraph import connected_components, dijkstra
from skimage.graph import pixel_graph
from skimage.morphology import skeletonize

from pipeline.checks import check_choice
from pipeline.errors import ConfigError, ShapeError
from pipeline.shapes.polyline import points_at_arc_length, polyline_arc_length

__all__ = [
    "DISTANCE_METHODS",
    "clean_mask",
    "join_pieces",
    "skeleton_path",
    "arc_length_keypoints",
    "keypoint_parameters",
    "distance_to_mask",
    "exact_distance_transform",
    "foreground_window",
    "outline_length",
]

DISTANCE_METHODS = ("exact", "kornia")


def join_pieces(mask: np.ndarray, *, min_fraction: float = 0.2, max_gap_radii: float = 4.0) -> np.ndarray:
    """Join pieces of a tube-like object cut apart by an occluder to its largest piece by straight bridges.

    A piece (an 8-connected component other than the largest) is joined when its area is at least
    ``min_fraction`` of the largest piece's and its nearest pixel lies within ``max_gap_radii`` times the largest
    piece's radius ``r`` (its largest inscribed radius) of it. The bridge is a line of round caps between the two
    pieces' ends (``piece_ends``: the centroids of each piece's pixels within ``2 r`` of the nearest pair), as thick
    as the thinner end (twice the largest inscribed radius among those pixels). Pieces are joined in turn, nearest
    first, until none qualifies; a mask of one piece comes back unchanged.

    Args:
        mask: ``(H, W)`` bool, True on the robot.
        min_fraction: smallest piece joined, as a fraction of the largest piece's area.
        max_gap_radii: largest gap bridged, in radii of the largest piece.

    Returns:
        ``(H, W)`` bool, a copy.
    """
    check_mask(mask)
    if one_piece(mask):  # the common case
        return mask.copy()
    out = mask.copy()
    while True:
        count, labels, stats, _ = cv2.connectedComponentsWithStats(out.astype(np.uint8), connectivity=8)
        if count <= 2:
            return out
        areas = stats[1:, cv2.CC_STAT_AREA]
        largest = 1 + int(np.argmax(areas))
        main = labels == largest
        outside = cv2.distanceTransform((~main).astype(np.uint8), cv2.DIST_L2, 5)  # (H, W) px to the main piece
        inside = cv2.distanceTransform(main.astype(np.uint8), cv2.DIST_L2, 5)  # and its inscribed radii
        best = None
        for label in range(1, count):
            if label == largest or areas[label - 1] < min_fraction * areas[largest - 1]:
                continue
            ends = piece_ends(main, labels == label, outside, inside, max_gap_radii=max_gap_radii)
            if ends is not None and (best is None or ends[0] < best[0]):
                best = ends
        if best is None:
            return out
        _, ((u0, v0), (u1, v1)), radii = best
        bridge = np.zeros(out.shape, np.uint8)
        cv2.line(bridge, (int(round(u0)), int(round(v0))), (int(round(u1)), int(round(v1))), 1,
                 max(1, int(round(2.0 * min(radii)))))
        out |= bridge > 0


def piece_ends(main: np.ndarray, piece: np.ndarray, outside: np.ndarray | None = None,
               inside: np.ndarray | None = None, *, max_gap_radii: float = 4.0, near_px: float | None = None
               ) -> tuple[float, np.ndarray, tuple[float, float]] | None:
    """Where two pieces of a tube cut by an occluder face each other, as ``join_pieces`` bridges them.

    Args:
        main: ``(H, W)`` bool, the piece whose radius ``r`` (largest inscribed radius, at least 1 px) sets the reach.
        piece: ``(H, W)`` bool, the other piece (not touching ``main``).
        outside: ``(H, W)`` float32, every pixel's distance to ``main`` (``cv2.distanceTransform`` of its
            complement), computed when ``None``.
        inside: ``(H, W)`` float32, ``main``'s inscribed radii (``cv2.distanceTransform`` of it), computed when
            ``None``.
        max_gap_radii: the largest gap, in radii ``r``.
        near_px: how far from the nearest pair a pixel belongs to an end, pixels (``None``: ``2 r``, the bridge's).

    Returns:
        ``None`` when ``piece``'s nearest pixel lies farther than ``max_gap_radii * r`` from ``main`` (or either is
        empty); else ``(gap, ends, radii)``: the gap in pixels, ``ends (2, 2)`` the ``(u, v)`` centroids of
        ``main``'s and ``piece``'s pixels within ``near_px`` of the nearest pair, and ``radii`` the largest inscribed
        radius among those pixels of each (the facing ends' half-widths).
    """
    if not main.any() or not piece.any():
        return None
    if outside is None:
        outside = cv2.distanceTransform((~main).astype(np.uint8), cv2.DIST_L2, 5)
    if inside is None:
        inside = cv2.distanceTransform(main.astype(np.uint8), cv2.DIST_L2, 5)
    radius = max(float(inside.max()), 1.0)
    rows, cols = np.nonzero(piece)
    i = int(np.argmin(outside[rows, cols]))
    gap = float(outside[rows[i], cols[i]])
    if gap > max_gap_radii * radius:
        return None
    rows_main, cols_main = np.nonzero(main)
    main_points = np.stack([cols_main, rows_main], axis=1).astype(np.float64)
    piece_points = np.stack([cols, rows], axis=1).astype(np.float64)
    q = piece_points[i]
    p = main_points[np.argmin(((main_points - q) ** 2).sum(1))]  # the nearest pair (p, q)
    ends, radii = [], []
    reach = 2.0 * radius if near_px is None else float(near_px)
    piece_inside = cv2.distanceTransform(piece.astype(np.uint8), cv2.DIST_L2, 5)
    for points, corner, depth in ((main_points, p, inside), (piece_points, q, piece_inside)):
        near = ((points - corner) ** 2).sum(1) <= reach**2
        ends.append(points[near].mean(axis=0))
        radii.append(float(depth[points[near][:, 1].astype(int), points[near][:, 0].astype(int)].max()))
    return gap, np.array(ends), (radii[0], radii[1])


def clean_mask(mask: np.ndarray, min_hole_px: int = 64) -> np.ndarray:
    """Keep the largest 8-connected component of ``mask`` and fill its holes smaller than ``min_hole_px`` pixels.

    A hole is a 4-connected background region that does not touch the image border; holes of at least
    ``min_hole_px`` pixels are kept (a real gap, e.g. an arm curling back on itself).

    Args:
        mask: ``(H, W)`` bool, True on the robot.
        min_hole_px: smallest hole area (pixels) that is kept; ``0`` fills no hole.

    Returns:
        ``(H, W)`` bool.

    Raises:
        ShapeError: ``mask is empty`` (no True pixel), or not an ``(H, W)`` bool array.
    """
    check_mask(mask)
    if isinstance(min_hole_px, bool) or not isinstance(min_hole_px, int) or min_hole_px < 0:
        raise ConfigError(f"min_hole_px: expected an int >= 0, got {min_hole_px!r}")
    # Both passes work in a box: the mask's True pixels' box (every component lies in it), then the largest
    # component's (its holes do). A background region of that box that reaches the box's edge continues outside
    # it (every pixel next to the box is background), so it is a hole in the box exactly when it is one in the
    # image (a tube in a 640x360 image: a ninth of the time).
    H, W = mask.shape
    x0, y0, w0, h0 = cv2.boundingRect(mask.view(np.uint8))
    count, labels, stats, _ = cv2.connectedComponentsWithStats(mask[y0:y0 + h0, x0:x0 + w0].view(np.uint8),
                                                               connectivity=8)
    largest = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))  # label 0 is the background
    bx0, by0, bw, bh = (int(v) for v in stats[largest, :4])
    kept = labels[by0:by0 + bh, bx0:bx0 + bw] == largest
    # Not skimage's remove_small_holes: it also fills small background pockets open to the image border.
    count, labels, stats, _ = cv2.connectedComponentsWithStats((~kept).view(np.uint8), connectivity=4)
    h_box, w_box = kept.shape
    x, y = stats[:, cv2.CC_STAT_LEFT], stats[:, cv2.CC_STAT_TOP]
    w, h = stats[:, cv2.CC_STAT_WIDTH], stats[:, cv2.CC_STAT_HEIGHT]
    inner = (x > 0) & (y > 0) & (x + w < w_box) & (y + h < h_box)  # not reaching the box's edge
    small = inner & (stats[:, cv2.CC_STAT_AREA] < min_hole_px)
    small[0] = False  # label 0 of the inverted image is the robot itself
    out = np.zeros((H, W), bool)
    out[y0 + by0:y0 + by0 + bh, x0 + bx0:x0 + bx0 + bw] = kept | small[labels]
    return out


def skeleton_path(
    mask: np.ndarray, base_pixel: tuple[float, float] | None = None, *, extend_to_boundary: bool = True
) -> np.ndarray:
    """The mask's centreline in the image as one ordered pixel path from the base to the tip.

    Steps: ``skimage.morphology.skeletonize``; the 8-connected graph of skeleton pixels (edge weights 1 and
    sqrt(2)), its largest connected component; the longest geodesic path found by two Dijkstra sweeps (exact on a
    tree; side branches, spurs, are dropped). A skeleton stops about one radius ``r`` short of each end of a
    thick shape, and forks there towards the corners of a flat end; so with ``extend_to_boundary`` the path is
    first cut back to the last fork (a side branch of 2+ pixels) within ``2 r + 2`` px of each end (``r`` the
    distance from the fork to the background), then each end is extended straight, along the path's direction
    over its last ``2 r`` (at least 3 px), to the last mask pixel on that line.

    Base end: the end nearest ``base_pixel`` when given; otherwise the end nearest the image border (arms enter
    the image from its edge); the first end found on a tie.

    Args:
        mask: ``(H, W)`` bool robot mask (clean it first with ``clean_mask``).
        base_pixel: ``(u, v)`` of the arm's base in pixels, or ``None`` meaning *unknown* (border rule above).
        extend_to_boundary: extend both ends to the mask boundary.

    Returns:
        ``(P, 2)`` float64 pixel coordinates ``(u, v)``, ordered base to tip, ``P >= 2``.

    Raises:
        ShapeError: ``mask is empty``, or ``mask skeleton has no path (fewer than 2 pixels)``.
    """
    check_mask(mask)
    skeleton = skeletonize(mask)
    count = int(skeleton.sum())
    if count < 2:
        raise ShapeError(f"mask skeleton has no path (fewer than 2 pixels): {count} skeleton pixel(s)")
    path_rc = _longest_geodesic_path(skeleton)  # (P, 2) (row, col)
    if extend_to_boundary:
        inside = exact_distance_transform(mask)
        path_rc = _trim_end_forks(path_rc, skeleton, inside)
        path = path_rc[:, ::-1].astype(np.float64)  # (P, 2) (u, v)
        path = _extend_end(_extend_end(path, mask, inside)[::-1], mask, inside)[::-1]
    else:
        path = path_rc[:, ::-1].astype(np.float64)
    H, W = mask.shape
    if base_pixel is not None:
        base = np.asarray(base_pixel, dtype=np.float64)
        if base.shape != (2,) or not np.isfinite(base).all():
            raise ConfigError(f"base_pixel: expected (u, v), two finite numbers, got {base_pixel!r}")
        d_first, d_last = (float(np.linalg.norm(p - base)) for p in (path[0], path[-1]))
    else:
        d_first, d_last = (min(p[0], p[1], W - 1 - p[0], H - 1 - p[1]) for p in (path[0], path[-1]))
    return path if d_first <= d_last else path[::-1].copy()


def keypoint_parameters(k: int = 4, include_tip: bool = True) -> np.ndarray:
    """Fractions of arc length of the keypoints: ``(K,)`` float64, ``K = k``.

    ``include_tip=True``: ``s_j = j / k`` for ``j = 1..k`` (k = 4: 0.25, 0.5, 0.75, 1.0, the last one the tip).
    ``include_tip=False``: ``s_j = j / (k + 1)`` (k = 4: 0.2, 0.4, 0.6, 0.8, interior only).
    The base (``s = 0``) is never a keypoint: it is often cut by the image border or hidden by the mount.
    """
    if isinstance(k, bool) or not isinstance(k, int) or k < 1:
        raise ConfigError(f"k: expected an int >= 1 (number of keypoints), got {k!r}")
    j = np.arange(1, k + 1, dtype=np.float64)
    return j / k if include_tip else j / (k + 1)


def arc_length_keypoints(path: np.ndarray, k: int = 4, include_tip: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """``k`` points along an ordered path, evenly spaced by arc length, at ``s = keypoint_parameters(k, include_tip)``.

    ``s`` is the fraction of the *image* path length from the base. A fit matches keypoint ``j`` to the curve
    point of the same fraction of projected length (the Bezier parameter equals it only for uniform speed).

    Args:
        path: ``(P, 2)`` pixel path ``(u, v)`` ordered base to tip (``skeleton_path``).
        k: number of keypoints.
        include_tip: whether the last keypoint is the tip (see ``keypoint_parameters``).

    Returns:
        ``(points (K, 2) float64 pixels (u, v), s (K,) float64 in (0, 1])``.

    Raises:
        ShapeError: the path has zero length.
    """
    if not isinstance(path, np.ndarray) or path.ndim != 2 or path.shape[1] != 2 or path.shape[0] < 2:
        got = f"{path.shape}" if isinstance(path, np.ndarray) else type(path).__name__
        raise ShapeError(f"path: expected a (P, 2) array with P >= 2, got {got}")
    s = keypoint_parameters(k, include_tip)
    total = polyline_arc_length(path)[-1]
    if total <= 0:
        raise ShapeError("path: has zero length (all points equal)")
    return points_at_arc_length(path, s * total), s


def distance_to_mask(mask: torch.Tensor, method: str = "exact") -> torch.Tensor:
    """Euclidean distance (pixels) from each pixel to the nearest mask pixel; 0 on the mask.

    ``"exact"``: :func:`exact_distance_transform` on the CPU (exact and bit-reproducible), moved to the mask's
    device; the default. ``"kornia"``: ``kornia.contrib.distance_transform`` on the mask's device; an
    approximation (kornia 0.9 documents up to 29 % short on diagonals; we measured up to 34 % relative on a
    360 x 640 scene) and slower on a CPU, kept for masks that live on a GPU.

    Args:
        mask: ``(H, W)`` bool, or float in [0, 1] (robot where > 0.5).
        method: ``"exact"`` or ``"kornia"``.

    Returns:
        ``(H, W)`` float32 on the device of ``mask``.

    Raises:
        ShapeError: ``mask is empty``, or not ``(H, W)``.
    """
    check_choice(method, DISTANCE_METHODS, "distance method")
    if not isinstance(mask, torch.Tensor) or mask.dim() != 2:
        got = tuple(mask.shape) if isinstance(mask, torch.Tensor) else type(mask).__name__
        raise ShapeError(f"mask: expected an (H, W) torch.Tensor, got {got}")
    robot = mask if mask.dtype == torch.bool else mask > 0.5
    if not bool(robot.any()):
        raise ShapeError("mask is empty: no robot pixel to measure the distance to")
    if method == "kornia":
        from kornia.contrib import distance_transform

        return distance_transform(robot.to(torch.float32)[None, None])[0, 0]
    distance = exact_distance_transform((~robot).cpu().numpy()).astype(np.float32)
    return torch.from_numpy(distance).to(mask.device)


def exact_distance_transform(foreground: np.ndarray) -> np.ndarray:
    """Euclidean distance (pixels) from each non-zero pixel of ``foreground`` to the nearest zero pixel; 0 on zeros.

    Exact (the square root of an integer squared distance, float64, ``scipy.ndimage.distance_transform_edt``) and
    bit-reproducible. Not OpenCV's ``distanceTransform(..., DIST_MASK_PRECISE)``: it computes the same distances
    in float32, but its vectorised path depends on the memory alignment of the output buffer, so the same mask
    gave distances differing in the last bits from call to call; through the distance loss's gradient that made
    pose fits of the same input differ now and then (``docs/decisions.md``, "Distance transform").

    Args:
        foreground: ``(H, W)`` bool or integer array.

    Returns:
        ``(H, W)`` float64.

    Raises:
        ShapeError: not ``(H, W)``, or no zero pixel (the distance is undefined).
    """
    if not isinstance(foreground, np.ndarray) or foreground.ndim != 2:
        got = foreground.shape if isinstance(foreground, np.ndarray) else type(foreground).__name__
        raise ShapeError(f"foreground: expected an (H, W) array, got {got}")
    nonzero = foreground != 0
    if nonzero.all():
        raise ShapeError("foreground has no zero pixel: no pixel to measure the distance to")
    # Computed on the foreground's bounding box grown by one pixel: every foreground pixel lies in it, and its
    # nearest zero pixel too (a zero pixel outside, clamped onto the box's border ring of zeros, comes nearer),
    # so the distances are the same, at a fraction of a large image's time.
    window = foreground_window(nonzero, 1)
    if window is None:
        return np.zeros(nonzero.shape, dtype=np.float64)
    if nonzero[window].shape == nonzero.shape:  # the box is the image (a background's distances): no copy
        return distance_transform_edt(nonzero)
    distance = np.zeros(nonzero.shape, dtype=np.float64)
    distance[window] = distance_transform_edt(nonzero[window])
    return distance


def foreground_window(mask: np.ndarray, margin: int) -> tuple[slice, slice] | None:
    """``(rows, cols)`` slices of the bounding box of ``mask (H, W)``'s non-zero pixels grown by ``margin`` pixels
    on every side (clipped to the image), or ``None`` when it has none: the part of the image that local
    operations on the mask (distance transforms, skeletons, dilations by at most ``margin - 1``) need."""
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    if not len(rows):
        return None
    return (slice(max(int(rows[0]) - margin, 0), int(rows[-1]) + margin + 1),
            slice(max(int(cols[0]) - margin, 0), int(cols[-1]) + margin + 1))


def outline_length(contours) -> float:
    """Length, pixels, of OpenCV contours (``cv2.findContours(..., cv2.CHAIN_APPROX_NONE)``), each simplified to
    within 0.7 px: within 2.5 % of a digital disc's circumference, where the raw pixel chain and
    ``skimage.measure.perimeter`` are 5 % long."""
    return float(sum(cv2.arcLength(cv2.approxPolyDP(c, 0.7, True), True) for c in contours))


def one_piece(mask: np.ndarray) -> bool:
    """Whether a non-empty ``(H, W)`` bool mask is one 8-connected component (counted in the box of its True
    pixels: a tenth of the time of the whole image for a tube in a 640x360 frame)."""
    x, y, w, h = cv2.boundingRect(mask.view(np.uint8))
    return cv2.connectedComponents(mask[y:y + h, x:x + w].view(np.uint8), connectivity=8)[0] <= 2


def check_mask(mask: np.ndarray) -> None:
    """Raise ``ShapeError`` unless ``mask`` is a non-empty (H, W) bool array."""
    if not isinstance(mask, np.ndarray) or mask.ndim != 2 or mask.dtype != bool:
        got = f"{mask.dtype} {mask.shape}" if isinstance(mask, np.ndarray) else type(mask).__name__
        raise ShapeError(f"mask: expected an (H, W) bool array, got {got}")
    if not mask.any():
        raise ShapeError("mask is empty: no robot pixel")


def _longest_geodesic_path(skeleton: np.ndarray) -> np.ndarray:
    """Longest shortest path in the 8-connected graph of the ``(H, W)`` bool skeleton's pixels (largest component):
    ``(P, 2)`` (row, col)."""
    graph, pixels = pixel_graph(skeleton, connectivity=2)  # edge weights 1 and sqrt(2); nodes in raster order
    rows, cols = np.unravel_index(pixels, skeleton.shape)
    _, component = connected_components(graph, directed=False)
    largest = np.argmax(np.bincount(component))
    members = np.nonzero(component == largest)[0]
    if members.size < 2:
        raise ShapeError("mask skeleton has no path (fewer than 2 pixels) in its largest connected piece")
    first = dijkstra(graph, directed=False, indices=int(members[0]))
    u = int(np.argmax(np.where(np.isfinite(first), first, -1.0)))
    dist, predecessors = dijkstra(graph, directed=False, indices=u, return_predecessors=True)
    v = int(np.argmax(np.where(np.isfinite(dist), dist, -1.0)))
    nodes = [v]
    while nodes[-1] != u:
        nodes.append(int(predecessors[nodes[-1]]))
    nodes.reverse()
    return np.stack([rows[nodes], cols[nodes]], axis=1)


def _trim_end_forks(path_rc: np.ndarray, skeleton: np.ndarray, inside: np.ndarray) -> np.ndarray:
    """Cut ``path_rc`` (``(P, 2)`` (row, col)) back to the outermost fork within ``2 r + 2`` px of each end."""
    on_path = np.zeros_like(skeleton)
    on_path[path_rc[:, 0], path_rc[:, 1]] = True
    _, labels, stats, _ = cv2.connectedComponentsWithStats((skeleton & ~on_path).astype(np.uint8), connectivity=8)
    is_branch = stats[:, cv2.CC_STAT_AREA] >= 2
    is_branch[0] = False  # label 0: not an off-path skeleton pixel
    H, W = skeleton.shape
    fork = np.zeros(len(path_rc), dtype=bool)
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            r = np.clip(path_rc[:, 0] + dr, 0, H - 1)
            c = np.clip(path_rc[:, 1] + dc, 0, W - 1)
            fork |= is_branch[labels[r, c]]
    cumulative = polyline_arc_length(path_rc.astype(np.float64))
    reach = 2.0 * inside[path_rc[:, 0], path_rc[:, 1]] + 2.0  # (P,)
    near_base = np.nonzero(fork & (cumulative <= reach))[0]
    near_tip = np.nonzero(fork & (cumulative[-1] - cumulative <= reach))[0]
    first = int(near_base.max()) if near_base.size else 0
    last = int(near_tip.min()) if near_tip.size else len(path_rc) - 1
    if last - first < 1:
        return path_rc
    return path_rc[first : last + 1]


def _extend_end(path: np.ndarray, mask: np.ndarray, inside: np.ndarray, step_px: float = 0.5) -> np.ndarray:
    """Extend the last point of ``path`` (``(P, 2)`` (u, v)) straight to the last mask pixel along its direction."""
    end = path[-1]
    radius = float(inside[int(round(end[1])), int(round(end[0]))])
    cumulative = polyline_arc_length(path)
    back = cumulative[-1] - min(max(2.0 * radius, 3.0), cumulative[-1])
    start = np.array([np.interp(back, cumulative, path[:, d]) for d in range(2)])
    direction = end - start
    norm = float(np.linalg.norm(direction))
    if norm == 0:
        return path
    direction /= norm
    H, W = mask.shape
    last = end
    for i in range(1, int(2 * (H + W) / step_px)):
        p = end + i * step_px * direction
        u, v = int(round(p[0])), int(round(p[1]))
        if not (0 <= u < W and 0 <= v < H and mask[v, u]):
            break
        last = p
    if last is end:
        return path
    return np.concatenate([path, last[None]], axis=0)
