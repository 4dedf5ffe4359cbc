"""Auto segmenter: the shipped network's mask, refined by a colour model of this image (GrabCut).

Works on an arm of any colour: nothing about the arm's colour is configured. The network (``OnnxSegmenter``)
gives a first mask; GrabCut (OpenCV: Gaussian-mixture colour models of arm and background estimated from the image
itself, and a graph cut that follows colour edges) then moves its rim within ``band_px`` of where the network put
it. The network learnt its rim from training renders; the colour models put the rim where the image's colours
change, which keeps the mask's area (the apparent width the shape fit reads depth from) unbiased.

GrabCut's labels, in a crop around the first mask (``4 * band_px`` margin): sure arm = the first mask eroded by
``band_px``; probable arm = the rest of the first mask; probable background = the ring ``band_px`` wide around it;
sure background = everything farther. An empty first mask stays empty (the caller reports it); a first mask with
no sure-background pixel around it in the image is returned unrefined.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from pipeline.errors import ConfigError, ShapeError
from pipeline.segment.base import check_bgr_image, check_frame_index, largest_component
from pipeline.segment.onnx_model import DEFAULT_ONNX_MODEL, OnnxSegmenter, OnnxSegmenterConfig

#: The seed of OpenCV's random generator (the calling thread's) before each GrabCut: a frame's mask depends on the
#: image alone, not on what ran before it. (It also resets that generator for the caller's later OpenCV calls.)
GRABCUT_SEED = 0


def _int_at_least(value: object, low: int, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low:
        raise ConfigError(f"{name}: expected an int >= {low}, got {value!r}")
    return int(value)


@dataclass(frozen=True, kw_only=True)
class AutoSegmenterConfig:
    """Settings of :class:`AutoSegmenter`.

    Attributes:
        model, device, num_threads, max_side: the first mask's network (see ``OnnxSegmenterConfig``).
        band_px: how far (pixels) the refinement may move the first mask's rim, inwards and outwards.
        iterations: GrabCut iterations (colour model re-estimated, graph cut again).
        largest_component: keep only the largest 8-connected component (of the first and the refined mask);
            ``False``: every component, the large ones refined each on its own (``refine_components``).
    """

    model: str = DEFAULT_ONNX_MODEL
    device: str = "auto"
    num_threads: int = 0
    max_side: int | None = None
    band_px: int = 6
    iterations: int = 3
    largest_component: bool = True

    def __post_init__(self) -> None:
        _int_at_least(self.band_px, 1, "band_px")
        _int_at_least(self.iterations, 1, "iterations")
        self.network()  # validates model, device, num_threads, max_side, largest_component

    def network(self) -> OnnxSegmenterConfig:
        """The config of the first mask's network."""
        return OnnxSegmenterConfig(model=self.model, device=self.device, num_threads=self.num_threads,
                                   max_side=self.max_side, largest_component=self.largest_component)


class AutoSegmenter:
    """Network mask refined by GrabCut; see the module docstring. Picklable (the network loads again)."""

    def __init__(self, config: AutoSegmenterConfig) -> None:
        if not isinstance(config, AutoSegmenterConfig):
            raise ConfigError(f"config: expected an AutoSegmenterConfig, got {type(config).__name__}")
        self.config = config
        self.network = OnnxSegmenter(config.network())

    def __call__(self, image: np.ndarray, *, frame_index: int = 0) -> np.ndarray:
        """``(H, W, 3)`` uint8 BGR -> ``(H, W)`` bool; ``frame_index`` is ignored."""
        check_bgr_image(image)
        check_frame_index(frame_index)
        first = self.network(image)
        if not self.config.largest_component:
            return refine_components(image, first, band_px=self.config.band_px, iterations=self.config.iterations)
        refined = grabcut_refine(image, first, band_px=self.config.band_px, iterations=self.config.iterations)
        return largest_component(refined)

    def __reduce__(self) -> tuple:
        return (AutoSegmenter, (self.config,))

    def __repr__(self) -> str:
        return f"AutoSegmenter({self.config!r})"


#: ``refine_components`` refines the components of at least this fraction of the largest one's area.
REFINE_COMPONENT_FRACTION = 0.1


def refine_components(image: np.ndarray, first_mask: np.ndarray, *, band_px: int = 6, iterations: int = 3
                      ) -> np.ndarray:
    """``grabcut_refine`` of each large 8-connected component of ``first_mask`` on its own (at least
    ``REFINE_COMPONENT_FRACTION`` of the largest's area; smaller ones kept as they are), united.

    Each large component is refined in its own crop, as it would be if it were the only one: a component's mask does
    not depend on what else the network marked (the largest is what ``grabcut_refine`` of the largest component
    alone gives), and scattered specks do not widen the crop (GrabCut's time grows with it).

    Returns:
        ``(H, W)`` bool.
    """
    H, W = check_bgr_image(image)
    _check_first_mask(first_mask, (H, W))
    count, labels, stats, _ = cv2.connectedComponentsWithStats(first_mask.astype(np.uint8), connectivity=8)
    if count <= 2:
        return grabcut_refine(image, first_mask, band_px=band_px, iterations=iterations)
    areas = stats[1:, cv2.CC_STAT_AREA]
    large = 1 + np.nonzero(areas >= REFINE_COMPONENT_FRACTION * areas.max())[0]
    out = first_mask & ~np.isin(labels, large)
    for label in large:
        out |= grabcut_refine(image, labels == label, band_px=band_px, iterations=iterations)
    return out


def _check_first_mask(first_mask: object, image_size: tuple[int, int]) -> None:
    """Raise ``ShapeError`` unless ``first_mask`` is an ``(H, W)`` bool array of the image's size."""
    H, W = image_size
    if not isinstance(first_mask, np.ndarray) or first_mask.shape != (H, W) or first_mask.dtype != bool:
        got = f"{first_mask.dtype} {first_mask.shape}" if isinstance(first_mask, np.ndarray) else type(first_mask)
        raise ShapeError(f"first_mask: expected an ({H}, {W}) bool array (the image's size), got {got}")


def grabcut_refine(image: np.ndarray, first_mask: np.ndarray, *, band_px: int = 6, iterations: int = 3) -> np.ndarray:
    """Move the rim of ``first_mask`` onto the image's colour edges (GrabCut), at most ``band_px`` either way.

    Args:
        image: ``(H, W, 3)`` uint8 BGR.
        first_mask: ``(H, W)`` bool, a first guess of the object (e.g. a network's).
        band_px: width of the band on each side of the first rim where GrabCut decides, pixels.
        iterations: GrabCut iterations.

    Returns:
        ``(H, W)`` bool: the first mask eroded by ``band_px``, plus what GrabCut keeps of the band; the first
        mask itself when it is empty or when no pixel of the crop is sure background.
    """
    H, W = check_bgr_image(image)
    _check_first_mask(first_mask, (H, W))
    band_px = _int_at_least(band_px, 1, "band_px")
    iterations = _int_at_least(iterations, 1, "iterations")
    if not first_mask.any():
        return first_mask.copy()
    rows, cols = np.nonzero(first_mask)
    margin = 4 * band_px
    y0, y1 = max(int(rows.min()) - margin, 0), min(int(rows.max()) + margin + 1, H)
    x0, x1 = max(int(cols.min()) - margin, 0), min(int(cols.max()) + margin + 1, W)
    first = first_mask[y0:y1, x0:x1].astype(np.uint8)
    disk = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * band_px + 1, 2 * band_px + 1))
    labels = np.full(first.shape, cv2.GC_BGD, np.uint8)
    labels[cv2.dilate(first, disk) > 0] = cv2.GC_PR_BGD
    labels[first > 0] = cv2.GC_PR_FGD
    labels[cv2.erode(first, disk) > 0] = cv2.GC_FGD
    if not (labels == cv2.GC_BGD).any():
        return first_mask.copy()
    background_model, foreground_model = np.zeros((1, 65)), np.zeros((1, 65))
    # GrabCut seeds its colour models' k-means from OpenCV's random generator of the calling thread, whose state
    # every earlier call moved on: without a fixed seed the same image gave masks up to 2.5 % apart (docs/segmenters.md)
    cv2.setRNGSeed(GRABCUT_SEED)
    cv2.grabCut(np.ascontiguousarray(image[y0:y1, x0:x1]), labels, None, background_model, foreground_model,
                iterations, cv2.GC_INIT_WITH_MASK)
    out = np.zeros((H, W), bool)
    out[y0:y1, x0:x1] = (labels == cv2.GC_FGD) | (labels == cv2.GC_PR_FGD)
    return out
