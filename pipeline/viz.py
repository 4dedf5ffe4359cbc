"""Pictures a person can look at: overlays on the input image and loss-history plots (OpenCV only).

Images are (H, W, 3) uint8 BGR as OpenCV reads them; pixel coordinates are (u, v) = (column, row) with pixel
centres at integers. Every function returns a new image and leaves its input untouched.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import cv2
import numpy as np

from pipeline.errors import ShapeError

GREEN = (0, 220, 0)
RED = (0, 0, 255)
BLUE = (255, 64, 0)
YELLOW = (0, 230, 230)
MAGENTA = (255, 0, 255)
WHITE = (255, 255, 255)
_SUB = 4  # sub-pixel bits for cv2 drawing
_SCALE = 1 << _SUB


def gray_to_bgr(mask: np.ndarray) -> np.ndarray:
    """(H, W) bool or [0, 1] float mask -> (H, W, 3) uint8 grey image."""
    m = np.asarray(mask, dtype=np.float32)
    return cv2.cvtColor((np.clip(m, 0, 1) * 255).astype(np.uint8), cv2.COLOR_GRAY2BGR)


def draw_outline(image: np.ndarray, silhouette: np.ndarray, color=GREEN, thickness: int = 2) -> np.ndarray:
    """Outline of ``silhouette > 0.5`` (H, W) drawn on a copy of ``image``."""
    _check_image(image)
    if silhouette.shape != image.shape[:2]:
        raise ShapeError(f"silhouette: expected shape {image.shape[:2]}, got {silhouette.shape}")
    binary = (np.asarray(silhouette) > 0.5).astype(np.uint8)
    contours, _ = cv2.findContours(binary, cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
    out = image.copy()
    cv2.drawContours(out, contours, -1, color, thickness, lineType=cv2.LINE_AA)
    return out


def draw_polyline(image: np.ndarray, points_px: np.ndarray, color=RED, thickness: int = 2) -> np.ndarray:
    """Open polyline through ``points_px`` (N, 2) (u, v)."""
    _check_image(image)
    out = image.copy()
    pts = _fixed(points_px)
    if len(pts) >= 2:
        cv2.polylines(out, [pts], False, color, thickness, lineType=cv2.LINE_AA, shift=_SUB)
    return out


def draw_points(
    image: np.ndarray,
    points_px: np.ndarray,
    color=YELLOW,
    radius: int = 4,
    labels: Sequence[str] | None = None,
) -> np.ndarray:
    """Filled circles at ``points_px`` (K, 2), optionally labelled."""
    _check_image(image)
    out = image.copy()
    for n, p in enumerate(_fixed(points_px)):
        cv2.circle(out, tuple(int(c) for c in p), radius * _SCALE, color, -1, lineType=cv2.LINE_AA, shift=_SUB)
        if labels is not None:
            org = (int(p[0]) // _SCALE + radius + 2, int(p[1]) // _SCALE - radius - 2)
            cv2.putText(out, labels[n], org, cv2.FONT_HERSHEY_SIMPLEX, 0.45, color, 1, cv2.LINE_AA)
    return out


def draw_frames(
    image: np.ndarray,
    T_cam_frames: np.ndarray,
    K: np.ndarray,
    axis_length_m: float = 0.05,
    thickness: int = 2,
) -> np.ndarray:
    """Coordinate frames (x red, y green, z blue) of poses ``T_cam_frames`` (L, 4, 4), camera frame, metres.

    Axes with an end at or behind the camera (z <= 1 mm) are skipped."""
    _check_image(image)
    T = np.asarray(T_cam_frames, dtype=np.float64).reshape(-1, 4, 4)
    out = image.copy()
    for pose in T:
        origin = pose[:3, 3]
        for axis, color in zip(range(3), (RED, GREEN, BLUE)):
            end = origin + axis_length_m * pose[:3, axis]
            if origin[2] <= 1e-3 or end[2] <= 1e-3:
                continue
            uv = _project(np.stack([origin, end]), K)
            cv2.line(out, tuple(int(c) for c in _fixed(uv[:1])[0]), tuple(int(c) for c in _fixed(uv[1:])[0]),
                     color, thickness, lineType=cv2.LINE_AA, shift=_SUB)
    return out


def plot_history(history: np.ndarray, *, title: str = "loss", best_start: int | None = None,
                 size: tuple[int, int] = (360, 560), labels: Sequence[str] = (),
                 colors: Sequence[tuple[int, int, int]] = ()) -> np.ndarray:
    """Loss curves (N iterations, S starts) on a log scale as a (H, W, 3) image; the best start in red. With
    ``labels`` and ``colors`` (one BGR colour and name per curve) every curve is drawn in its colour, with a legend."""
    h = np.asarray(history, dtype=np.float64)
    if h.ndim == 1:
        h = h[:, None]
    if h.ndim != 2 or h.shape[0] < 1:
        raise ShapeError(f"history: expected shape (N, S) with N >= 1, got {h.shape}")
    if len(labels) != len(colors) or (labels and len(labels) != h.shape[1]):
        raise ShapeError(f"labels, colors: expected none or one each per curve ({h.shape[1]}), got {len(labels)} "
                         f"labels and {len(colors)} colors")
    H, W = size
    out = np.full((H, W, 3), 255, np.uint8)
    left, right, top, bottom = 70, 15, 30, 40
    finite = h[np.isfinite(h) & (h > 0)]
    lo, hi = (float(finite.min()), float(finite.max())) if finite.size else (1.0, 10.0)
    lo_l, hi_l = math.floor(math.log10(lo)), math.ceil(math.log10(hi))
    hi_l = max(hi_l, lo_l + 1)
    n = max(h.shape[0] - 1, 1)

    def xy(i: np.ndarray, v: np.ndarray) -> np.ndarray:
        x = left + (W - left - right) * i / n
        y = top + (H - top - bottom) * (hi_l - np.log10(np.clip(v, 10.0**lo_l, None))) / (hi_l - lo_l)
        return np.stack([x, y], axis=-1)

    cv2.rectangle(out, (left, top), (W - right, H - bottom), (0, 0, 0), 1)
    for e in range(lo_l, hi_l + 1):
        y = int(xy(np.array([0.0]), np.array([10.0**e]))[0, 1])
        cv2.line(out, (left - 4, y), (W - right, y), (220, 220, 220), 1)
        cv2.putText(out, f"1e{e}", (8, y + 4), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    for frac in (0.0, 0.5, 1.0):
        x = int(left + (W - left - right) * frac)
        cv2.putText(out, str(int(round(frac * n))), (x - 8, H - bottom + 16), cv2.FONT_HERSHEY_SIMPLEX, 0.4,
                    (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(out, "iteration", (W // 2 - 30, H - 8), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(out, title, (left, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    order = [s for s in range(h.shape[1]) if s != best_start] + ([best_start] if best_start is not None else [])
    for s in order:
        ok = np.isfinite(h[:, s]) & (h[:, s] > 0)
        pts = xy(np.arange(h.shape[0])[ok].astype(np.float64), h[ok, s])
        color = colors[s] if colors else RED if s == best_start else (160, 160, 160)
        if len(pts) >= 2:
            cv2.polylines(out, [_fixed(pts)], False, color, 2 if s == best_start or colors else 1, cv2.LINE_AA,
                          shift=_SUB)
    for k, (label, color) in enumerate(zip(labels, colors)):  # legend, top right
        y = top + 18 + 18 * k
        cv2.line(out, (W - right - 250, y - 4), (W - right - 225, y - 4), color, 2, cv2.LINE_AA)
        cv2.putText(out, label, (W - right - 218, y), cv2.FONT_HERSHEY_SIMPLEX, 0.42, (0, 0, 0), 1, cv2.LINE_AA)
    return out


def _project(points_cam: np.ndarray, K: np.ndarray) -> np.ndarray:
    K = np.asarray(K, dtype=np.float64)
    p = points_cam @ K.T
    return p[:, :2] / p[:, 2:3]


def _fixed(points_px: np.ndarray) -> np.ndarray:
    """(N, 2) float pixel coordinates -> int32 fixed point for cv2 drawing with ``shift=_SUB``, clipped."""
    pts = np.asarray(points_px, dtype=np.float64).reshape(-1, 2)
    pts = np.clip(np.nan_to_num(pts, nan=-1e5), -1e5, 1e5)
    return np.round(pts * _SCALE).astype(np.int32)


def _check_image(image: np.ndarray) -> None:
    if not isinstance(image, np.ndarray) or image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
        raise ShapeError(f"image: expected an (H, W, 3) uint8 BGR array, got "
                         f"{getattr(image, 'shape', type(image))} {getattr(image, 'dtype', '')}")
