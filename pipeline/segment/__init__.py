"""Segmenters: ``(H, W, 3)`` uint8 BGR image -> ``(H, W)`` bool robot mask.

Three interchangeable kinds, each built from a small frozen config by :func:`make_segmenter` and called as
``segmenter(image, frame_index=0)``:

- ``color`` (:class:`ColorSegmenterConfig`): HSV thresholds (hue may wrap around red), opening, closing, largest
  component; named ranges in ``COLOR_PRESETS`` (``soft_arm`` fits the bundled soft-arm examples).
- ``onnx`` (:class:`OnnxSegmenterConfig`): a DeepLab-style network exported to ONNX with a ``meta.json``; the
  shipped ``robot_deeplab`` segments the soft arm and the example manipulator.
- ``file`` (:class:`FileSegmenterConfig`): masks read from disk, one path or a per-frame pattern.
- ``auto`` (:class:`AutoSegmenterConfig`): the network's mask refined by GrabCut with colour models estimated from
  the image itself (no colour to configure: arms of any colour); the soft-arm commands' default.
"""

from pipeline.segment.base import Segmenter, check_bgr_image, largest_component, mask_overlay
from pipeline.segment.color import (
    COLOR_PRESETS,
    ColorSegmenter,
    ColorSegmenterConfig,
    color_preset,
    parse_hsv,
    threshold_hsv,
)
from pipeline.segment.refine import AutoSegmenter, AutoSegmenterConfig, grabcut_refine, refine_components
from pipeline.segment.rim import image_rim_offset_px
from pipeline.segment.factory import SEGMENTER_KINDS, SegmenterConfig, make_segmenter
from pipeline.segment.file import FileSegmenter, FileSegmenterConfig
from pipeline.segment.onnx_model import (
    DEFAULT_ONNX_MODEL,
    SEGMENTER_MODELS_DIR,
    OnnxModelMeta,
    OnnxSegmenter,
    OnnxSegmenterConfig,
    load_onnx_meta,
    onnx_meta_from_dict,
    resolve_onnx_model,
)

__all__ = [
    "AutoSegmenter",
    "AutoSegmenterConfig",
    "COLOR_PRESETS",
    "DEFAULT_ONNX_MODEL",
    "SEGMENTER_KINDS",
    "SEGMENTER_MODELS_DIR",
    "ColorSegmenter",
    "ColorSegmenterConfig",
    "FileSegmenter",
    "FileSegmenterConfig",
    "OnnxModelMeta",
    "OnnxSegmenter",
    "OnnxSegmenterConfig",
    "Segmenter",
    "SegmenterConfig",
    "check_bgr_image",
    "color_preset",
    "grabcut_refine",
    "image_rim_offset_px",
    "refine_components",
    "largest_component",
    "load_onnx_meta",
    "make_segmenter",
    "mask_overlay",
    "onnx_meta_from_dict",
    "parse_hsv",
    "resolve_onnx_model",
    "threshold_hsv",
]
