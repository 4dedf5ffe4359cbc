"""Files on disk: JSON results, binary masks (uint8 0/255 PNG) and colour images (BGR, as OpenCV reads them)."""

from __future__ import annotations

import dataclasses
import json
import math
import os
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np
import torch

from pipeline.checks import check_image_size
from pipeline.errors import AssetError, ConfigError, ShapeError

#: Significant digits kept for floats written to JSON (1e-10 relative: sub-nanometre for metre-scale values).
JSON_FLOAT_DIGITS = 10


def write_json(path: str | Path, obj: object) -> None:
    """Write ``obj`` as indented JSON, creating parent folders; the file is replaced atomically.

    Tensors and arrays become nested lists, numpy scalars plain numbers, tuples lists, paths strings and
    dataclasses dicts. Floats are rounded to ``JSON_FLOAT_DIGITS`` significant digits; NaN and inf become ``null``
    (strict JSON has no such values).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    text = json.dumps(_to_json(obj), indent=2, allow_nan=False) + "\n"
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(text, encoding="utf-8")
    os.replace(tmp, path)


def json_line(obj: object) -> str:
    """``obj`` as one line of JSON (a JSON Lines record, without the newline), converted as ``write_json`` does."""
    return json.dumps(_to_json(obj), allow_nan=False, separators=(",", ":"))


def read_mask(path: str | Path, image_size: Sequence[int] | None = None) -> np.ndarray:
    """Read a mask image as an ``(H, W)`` bool array: grey value > 127 is robot.

    Args:
        path: any image OpenCV reads (colour images are converted to grey).
        image_size: expected ``(H, W)``; when given, a different size is a ``ConfigError``.

    Raises:
        AssetError: the file is missing or OpenCV cannot decode it.
        ConfigError: the size differs from ``image_size``.
    """
    path = Path(path)
    grey = _imread(path, cv2.IMREAD_GRAYSCALE, "mask")
    if image_size is not None:
        H, W = check_image_size(image_size)
        if grey.shape != (H, W):
            raise ConfigError(f"mask {path} is {grey.shape[1]}x{grey.shape[0]} but expected {W}x{H}")
    return grey > 127


def write_mask(path: str | Path, mask: np.ndarray) -> None:
    """Write an ``(H, W)`` bool mask as a uint8 0/255 PNG (or whatever format ``path``'s suffix names)."""
    if not isinstance(mask, np.ndarray) or mask.ndim != 2 or mask.dtype != bool:
        got = f"{mask.dtype} {mask.shape}" if isinstance(mask, np.ndarray) else type(mask).__name__
        raise ShapeError(f"mask: expected an (H, W) bool array (threshold it first), got {got}")
    _imwrite(Path(path), mask.astype(np.uint8) * 255)


def read_image(path: str | Path) -> np.ndarray:
    """Read a colour image as an ``(H, W, 3)`` uint8 BGR array (grey images are expanded to 3 channels).

    Raises:
        AssetError: the file is missing or OpenCV cannot decode it.
    """
    return _imread(Path(path), cv2.IMREAD_COLOR, "image")


def write_image(path: str | Path, image: np.ndarray) -> None:
    """Write an ``(H, W)`` or ``(H, W, 3)`` uint8 (BGR) image; the format follows the suffix of ``path``."""
    if not isinstance(image, np.ndarray) or image.dtype != np.uint8 or image.ndim not in (2, 3):
        got = f"{image.dtype} {image.shape}" if isinstance(image, np.ndarray) else type(image).__name__
        raise ShapeError(f"image: expected an (H, W) or (H, W, 3) uint8 array, got {got}")
    _imwrite(Path(path), image)


def _imread(path: Path, flags: int, what: str) -> np.ndarray:
    if not path.is_file():
        raise AssetError(f"{what} file not found: {path}")
    try:
        data = np.fromfile(path, dtype=np.uint8)  # avoids cv2.imread's silent None on non-ASCII paths
    except OSError as e:
        raise AssetError(f"cannot read {what} file {path}: {e}") from None
    image = cv2.imdecode(data, flags) if data.size else None
    if image is None:
        raise AssetError(f"cannot read {what} file {path}: not an image OpenCV can decode")
    return image


def _imwrite(path: Path, image: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    ok, data = cv2.imencode(path.suffix or ".png", image)
    if not ok:
        raise ConfigError(f"cannot encode an image for {path}; use a suffix OpenCV writes, such as .png")
    data.tofile(path)


def _to_json(obj: object) -> object:
    if isinstance(obj, torch.Tensor):
        obj = obj.detach().cpu().numpy()
    if isinstance(obj, np.ndarray):
        return _to_json(obj.tolist())
    if isinstance(obj, np.generic):
        return _to_json(obj.item())
    if isinstance(obj, bool) or obj is None or isinstance(obj, (int, str)):
        return obj
    if isinstance(obj, float):
        return float(f"{obj:.{JSON_FLOAT_DIGITS}g}") if math.isfinite(obj) else None
    if isinstance(obj, Path):
        return str(obj)
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: _to_json(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, dict):
        return {str(k): _to_json(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_to_json(v) for v in obj]
    raise ConfigError(f"write_json: cannot write a {type(obj).__name__} as JSON")
