"""Argument parsing helpers shared by the command modules."""

from __future__ import annotations

import re

from pipeline.errors import ConfigError

_WXH = re.compile(r"^\s*(\d+)\s*[xX]\s*(\d+)\s*$")


def parse_size_wh(text: str, option: str) -> tuple[int, int]:
    """Parse ``"WxH"`` (e.g. ``"640x480"``) into ``image_size`` ``(H, W)``; ``option`` names it in errors."""
    match = _WXH.match(text)
    if match is None or int(match[1]) <= 0 or int(match[2]) <= 0:
        raise ConfigError(f"{option}: expected WIDTHxHEIGHT with positive integers, like 640x480, got {text!r}")
    return (int(match[2]), int(match[1]))
