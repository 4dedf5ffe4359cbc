"""Argument parsing helpers shared by the command modules."""

from __future__ import annotations

import os
import re
from collections.abc import Callable, Hashable
from typing import TypeVar

from pipeline.errors import ConfigError

T = TypeVar("T")

_WXH = re.compile(r"^\s*(\d+)\s*[xX]\s*(\d+)\s*$")


def parse_size_wh(text: str, option: str) -> tuple[int, int]:
    """Parse ``"WxH"`` (e.g. ``"640x480"``) into ``image_size`` ``(H, W)``; ``option`` names it in errors."""
    match = _WXH.match(text)
    if match is None or int(match[1]) <= 0 or int(match[2]) <= 0:
        raise ConfigError(f"{option}: expected WIDTHxHEIGHT with positive integers, like 640x480, got {text!r}")
    return (int(match[2]), int(match[1]))


def add_rim_offset_argument(parser, *, auto: str, image: str) -> None:
    """``--rim-offset-px PX|auto|image`` of the soft-arm commands (``ShapeFitConfig.rim_offset_px``); ``auto`` and
    ``image`` say what each does in that command and when ``image`` is the default (the parsed default is ``None``:
    the command decides)."""
    parser.add_argument(
        "--rim-offset-px", type=parse_rim_offset, default=None, metavar="PX|auto|image",
        help="how far the masks' outline lies outside the arm's, pixels (positive: the segmenter's masks are too "
        "wide); the depth is read from the width, so a known bias is taken off (default 0 for masks: exact); auto: "
        f"{auto}; image: {image}",
    )  # fmt: skip


def parse_rim_offset(text: str) -> float | str:
    """``--rim-offset-px``: ``auto``, ``image`` or a number of pixels (argparse ``type``)."""
    import argparse

    if text in ("auto", "image"):
        return text
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number of pixels, auto or image, got {text!r}") from None


def loaded_once(args, key: Hashable, build: Callable[[], T]) -> T:
    """``build()``, or what it built for ``key`` before in this process when the caller put a ``model_cache`` dict
    on the parsed ``args`` (the batch workers do: robot models and segmenters load once per worker process); the
    single commands carry none and build every time. Keys that name files include their modification time."""
    cache = getattr(args, "model_cache", None)
    if cache is None:
        return build()
    try:
        hash(key)
    except TypeError:
        return build()
    if key not in cache:
        cache[key] = build()
    return cache[key]


def file_stamp(path: str) -> tuple[str, float]:
    """``(absolute path, modification time)`` of a file, for :func:`loaded_once` keys (``0.0`` if it is missing:
    the loader then reports it)."""
    absolute = os.path.abspath(path)
    return absolute, (os.path.getmtime(absolute) if os.path.exists(absolute) else 0.0)
