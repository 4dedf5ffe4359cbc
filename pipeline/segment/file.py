"""File segmenter: masks made elsewhere (by hand, by another tool), read from disk.

``pattern`` is a path, or a Python format string with the field ``frame`` for videos: ``masks/{frame:05d}.png``
reads ``masks/00012.png`` for frame 12. A pattern without ``{frame}`` is one mask used for every frame. Literal
braces in a path are written doubled (``{{`` and ``}}``). Masks are read as ``pipeline.io.read_mask`` does (grey
value > 127 is robot) and must have the image's size.
"""

from __future__ import annotations

import string
from dataclasses import dataclass

import numpy as np

from pipeline.errors import ConfigError
from pipeline.io import read_mask
from pipeline.segment.base import check_bgr_image, check_frame_index


@dataclass(frozen=True, kw_only=True)
class FileSegmenterConfig:
    """Settings of :class:`FileSegmenter`.

    Attributes:
        pattern: mask file path, or a format string with the field ``{frame}`` (format specs allowed, e.g.
            ``{frame:05d}``); see the module docstring.
    """

    pattern: str

    def __post_init__(self) -> None:
        if not isinstance(self.pattern, str) or not self.pattern:
            raise ConfigError(
                f"pattern: expected a mask path or pattern like masks/{{frame:05d}}.png, got {self.pattern!r}"
            )
        try:
            fields = [f for _, f, _, _ in string.Formatter().parse(self.pattern) if f is not None]
            unknown = [f for f in fields if f != "frame"]
            if not unknown:
                self.pattern.format(frame=0)
        except (ValueError, KeyError, IndexError, AttributeError) as e:
            raise ConfigError(
                f"pattern {self.pattern!r}: not a valid mask pattern ({type(e).__name__}: {e}); the only field is "
                "{frame}, e.g. masks/{frame:05d}.png (write literal braces as {{ and }})"
            ) from None
        if unknown:
            raise ConfigError(
                f"pattern {self.pattern!r}: unknown field(s) {', '.join(map(repr, unknown))}; "
                "the only field is {frame}, e.g. masks/{frame:05d}.png"
            )

    @property
    def per_frame(self) -> bool:
        """True when the pattern holds ``{frame}`` (one file per frame)."""
        return any(f is not None for _, f, _, _ in string.Formatter().parse(self.pattern))

    def path(self, frame_index: int) -> str:
        """The mask file of frame ``frame_index``."""
        return self.pattern.format(frame=check_frame_index(frame_index))


class FileSegmenter:
    """Reads the mask of each frame from disk; see :class:`FileSegmenterConfig`."""

    def __init__(self, config: FileSegmenterConfig) -> None:
        if not isinstance(config, FileSegmenterConfig):
            raise ConfigError(f"config: expected a FileSegmenterConfig, got {type(config).__name__}")
        self.config = config

    def __call__(self, image: np.ndarray, *, frame_index: int = 0) -> np.ndarray:
        """The mask of frame ``frame_index``: ``(H, W)`` bool, the size of ``image`` ``(H, W, 3)`` uint8 BGR.

        Raises:
            AssetError: the mask file is missing or unreadable.
            ConfigError: the mask's size differs from the image's.
        """
        H, W = check_bgr_image(image)
        return read_mask(self.config.path(frame_index), image_size=(H, W))

    def __repr__(self) -> str:
        return f"FileSegmenter({self.config!r})"
