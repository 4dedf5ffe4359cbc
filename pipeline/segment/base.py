"""The segmenter protocol and helpers shared by every segmenter.

Convention: images are ``(H, W, 3)`` uint8 BGR arrays as OpenCV reads them; masks are ``(H, W)`` bool arrays,
``True`` on the robot, the same size as the image.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import cv2
import numpy as np

from pipeline.errors import ShapeError


@runtime_checkable
class Segmenter(Protocol):
    """Image to robot mask. Build one from its config with ``pipeline.segment.make_segmenter``.

    ``frame_index`` is the frame's index in a video (0 for a single image). Only the file segmenter uses it (to
    pick the mask file of that frame); the others ignore it, so video code calls every segmenter the same way.
    """

    def __call__(self, image: np.ndarray, *, frame_index: int = 0) -> np.ndarray:
        """``(H, W, 3)`` uint8 BGR image -> ``(H, W)`` bool mask."""
        ...


def check_bgr_image(image: np.ndarray, name: str = "image") -> tuple[int, int]:
    """Raise ``ShapeError`` unless ``image`` is an ``(H, W, 3)`` uint8 array; return ``(H, W)``."""
    if not isinstance(image, np.ndarray):
        raise ShapeError(f"{name}: expected an (H, W, 3) uint8 BGR numpy array, got {type(image).__name__}")
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8 or min(image.shape[:2]) < 1:
        raise ShapeError(f"{name}: expected an (H, W, 3) uint8 BGR array, got {image.dtype} {image.shape}")
    return int(image.shape[0]), int(image.shape[1])


def check_frame_index(frame_index: int) -> int:
    """Raise ``ShapeError`` unless ``frame_index`` is an int >= 0."""
    if isinstance(frame_index, bool) or not isinstance(frame_index, (int, np.integer)) or frame_index < 0:
        raise ShapeError(f"frame_index: expected an int >= 0, got {frame_index!r}")
    return int(frame_index)


def largest_component(mask: np.ndarray) -> np.ndarray:
    """Keep the largest 8-connected component of an ``(H, W)`` bool mask (all ``False`` stays all ``False``)."""
    count, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    if count <= 2:  # background only, or one component
        return mask.copy()
    biggest = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    return labels == biggest


def mask_overlay(
    image: np.ndarray, mask: np.ndarray, color_bgr: tuple[int, int, int] = (0, 255, 0), alpha: float = 0.45
) -> np.ndarray:
    """The image with the mask tinted in ``color_bgr`` (weight ``alpha``) and its outline drawn.

    Args:
        image: ``(H, W, 3)`` uint8 BGR.
        mask: ``(H, W)`` bool.

    Returns:
        ``(H, W, 3)`` uint8 BGR.
    """
    H, W = check_bgr_image(image)
    if not isinstance(mask, np.ndarray) or mask.shape != (H, W) or mask.dtype != bool:
        got = f"{mask.dtype} {mask.shape}" if isinstance(mask, np.ndarray) else type(mask).__name__
        raise ShapeError(f"mask: expected an ({H}, {W}) bool array (the image's size), got {got}")
    out = image.copy()
    tint = np.empty_like(image)
    tint[:] = color_bgr
    blended = cv2.addWeighted(image, 1.0 - alpha, tint, alpha, 0.0)
    out[mask] = blended[mask]
    contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    cv2.drawContours(out, contours, -1, color_bgr, 1, cv2.LINE_AA)
    return out
