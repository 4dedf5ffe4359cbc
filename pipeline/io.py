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


@dataclasses.dataclass(frozen=True, kw_only=True, eq=False)
class JointTable:
    """Joint readings per video frame, as read from a CSV file by :func:`read_joints_csv`.

    Fields:
        path: the file it came from (named in errors).
        frames: ``(N,)`` int64 frame indices, increasing.
        time_s: ``(N,)`` float64 times in seconds (increasing), or ``None`` when the file has no ``time_s`` column.
        names: the ``J`` joint names (the other columns, in file order).
        values: ``(N, J)`` float64 readings, rad or m.
    """

    path: str
    frames: np.ndarray
    time_s: np.ndarray | None
    names: tuple[str, ...]
    values: np.ndarray

    def readings(self, frame: int, time_s: float | None = None, *, interpolate: bool = False) -> dict[str, float]:
        """The readings of ``frame`` by name: its row; with ``interpolate``, for a frame without a row, linear
        interpolation between the rows before and after it, by ``time_s`` where both the table and the caller
        have times, else by frame index.

        Raises:
            ConfigError: no row for the frame (without ``interpolate``), or a frame before the first or after the
                last row (no neighbours to interpolate from).
        """
        k = int(np.searchsorted(self.frames, frame))
        if k < len(self.frames) and self.frames[k] == frame:
            return dict(zip(self.names, self.values[k].tolist()))
        if not interpolate:
            raise ConfigError(f"{self.path}: no row for frame {frame} (rows cover frames {self.frames[0]}-"
                              f"{self.frames[-1]}, {len(self.frames)} rows; --interpolate-joints fills gaps)")
        if k == 0 or k == len(self.frames):
            raise ConfigError(f"{self.path}: frame {frame} is outside the rows' frames {self.frames[0]}-"
                              f"{self.frames[-1]}: nothing to interpolate from on one side")
        if self.time_s is not None and time_s is not None:
            t0, t1, t = self.time_s[k - 1], self.time_s[k], float(time_s)
        else:
            t0, t1, t = float(self.frames[k - 1]), float(self.frames[k]), float(frame)
        a = min(1.0, max(0.0, (t - t0) / (t1 - t0)))
        return dict(zip(self.names, ((1.0 - a) * self.values[k - 1] + a * self.values[k]).tolist()))


def read_joints_csv(path: str | Path, *, min_rows: int = 1) -> JointTable:
    """Read per-frame joint readings: a header row with ``frame``, optionally ``time_s``, and joint names; one row
    per frame (any order; sorted by frame).

    Raises:
        AssetError: the file is missing or unreadable.
        ConfigError: no ``frame`` column, a repeated column, fewer than ``min_rows`` rows, a row with another number
            of fields than the header, a value that is not a finite number (the message names the line and the
            column), a frame index that is not a non-negative integer or repeats, times that do not increase
            with the frames.
    """
    import csv

    path = Path(path)
    try:
        with path.open(newline="", encoding="utf-8") as file:
            reader = csv.reader(file)
            rows = [(reader.line_num, row) for row in reader if any(cell.strip() for cell in row)]
    except FileNotFoundError:
        raise AssetError(f"joints CSV not found: {path}") from None
    except (OSError, UnicodeDecodeError, csv.Error) as e:
        raise AssetError(f"cannot read joints CSV {path}: {e}") from None
    if not rows:
        raise ConfigError(f"{path}: empty; expected a header row with frame and joint names")
    header = [cell.strip() for cell in rows[0][1]]
    if "frame" not in header:
        raise ConfigError(f"{path}: the header has no 'frame' column (got {', '.join(header)})")
    repeated = sorted({name for name in header if header.count(name) > 1})
    if repeated or "" in header:
        raise ConfigError(f"{path}: header columns must be named once each, got {', '.join(header)}")
    body = rows[1:]
    if len(body) < min_rows:
        raise ConfigError(f"{path}: expected at least {min_rows} row(s) of readings, got {len(body)}")
    numbers = np.empty((len(body), len(header)))
    for i, (line, row) in enumerate(body):
        if len(row) != len(header):
            raise ConfigError(f"{path} line {line}: expected {len(header)} fields as the header, got {len(row)}")
        for j, cell in enumerate(row):
            try:
                numbers[i, j] = float(cell)
            except ValueError:
                numbers[i, j] = math.nan
            if not math.isfinite(numbers[i, j]):
                raise ConfigError(f"{path} line {line}, column {header[j]}: expected a finite number, got {cell!r}")
    frames = numbers[:, header.index("frame")]
    bad = np.flatnonzero((frames != np.round(frames)) | (frames < 0))
    if len(bad):
        line, row = body[bad[0]]
        raise ConfigError(f"{path} line {line}, column frame: expected a frame index (an integer >= 0), got "
                          f"{row[header.index('frame')]!r}")
    order = np.argsort(frames, kind="stable")
    numbers, frames = numbers[order], frames[order].astype(np.int64)
    repeats = frames[1:][np.diff(frames) == 0]
    if len(repeats):
        raise ConfigError(f"{path}: frame {repeats[0]} has more than one row")
    time_s = numbers[:, header.index("time_s")] if "time_s" in header else None
    if time_s is not None and (np.diff(time_s) <= 0).any():
        raise ConfigError(f"{path}: column time_s: expected times increasing with the frame index")
    joint_columns = [j for j, name in enumerate(header) if name not in ("frame", "time_s")]
    return JointTable(path=str(path), frames=frames, time_s=time_s, names=tuple(header[j] for j in joint_columns),
                      values=numbers[:, joint_columns])
