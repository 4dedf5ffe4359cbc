"""``make_segmenter``: the segmenter a config describes."""

from __future__ import annotations

from typing import Union

from pipeline.errors import ConfigError
from pipeline.segment.base import Segmenter
from pipeline.segment.color import ColorSegmenter, ColorSegmenterConfig
from pipeline.segment.file import FileSegmenter, FileSegmenterConfig
from pipeline.segment.onnx_model import OnnxSegmenter, OnnxSegmenterConfig
from pipeline.segment.refine import AutoSegmenter, AutoSegmenterConfig

#: Segmenter kinds by name (the CLI's ``--segmenter`` choices) and their config classes.
SEGMENTER_KINDS: dict[str, type] = {
    "color": ColorSegmenterConfig,
    "onnx": OnnxSegmenterConfig,
    "file": FileSegmenterConfig,
    "auto": AutoSegmenterConfig,
}

SegmenterConfig = Union[ColorSegmenterConfig, OnnxSegmenterConfig, FileSegmenterConfig, AutoSegmenterConfig]


def make_segmenter(config: SegmenterConfig) -> Segmenter:
    """Build the segmenter of ``config``: colour, ONNX, file or auto, chosen by the config's type.

    Configs are small frozen dataclasses (picklable), so a batch runner can ship the config and build the
    segmenter where it runs.

    Raises:
        ConfigError: ``config`` is not one of the segmenter configs; AssetError / ConfigError from the
            segmenter itself (e.g. a missing or malformed ONNX model).
    """
    if isinstance(config, ColorSegmenterConfig):
        return ColorSegmenter(config)
    if isinstance(config, OnnxSegmenterConfig):
        return OnnxSegmenter(config)
    if isinstance(config, FileSegmenterConfig):
        return FileSegmenter(config)
    if isinstance(config, AutoSegmenterConfig):
        return AutoSegmenter(config)
    names = ", ".join(cls.__name__ for cls in SEGMENTER_KINDS.values())
    raise ConfigError(f"config: expected one of {names}, got {type(config).__name__}")
