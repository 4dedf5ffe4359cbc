"""Pinhole camera with OpenCV distortion: intrinsics, JSON files, projection, resizing and undistortion.

Convention:
    Camera frame is OpenCV's (x right, y down, z forward), in metres. Pixel coordinates ``(u, v)`` are
    (column, row) with pixel *centres* at integer coordinates: the top-left pixel covers ``[-0.5, 0.5]^2``.
    ``image_size`` is ``(H, W)``; the camera JSON file names ``width`` and ``height`` explicitly.

Resizing an image from ``(H, W)`` to ``(H', W')`` maps ``u' = (u + 0.5) * sx - 0.5`` with ``sx = W' / W`` (and
likewise ``v`` with ``sy = H' / H``), which is what ``cv2.resize`` does; :func:`resize_camera` scales ``K`` to match.
"""

from __future__ import annotations

import json
import math
import operator
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
from kornia.geometry.conversions import denormalize_points_with_intrinsics

from pipeline.checks import check_image_size, check_positive, check_shape
from pipeline.errors import AssetError, ConfigError, ShapeError

#: Counts of distortion coefficients OpenCV accepts; order (k1, k2, p1, p2[, k3[, k4, k5, k6[, s1..s4[, tx, ty]]]]).
DIST_COUNTS = (0, 4, 5, 8, 12, 14)

_JSON_KEYS = ("K", "dist", "width", "height")


@dataclass(frozen=True, kw_only=True)
class Camera:
    """Intrinsics of one pinhole camera with optional OpenCV lens distortion.

    Attributes:
        K: 3x3 intrinsic matrix, row-major ``((fx, 0, cx), (0, fy, cy), (0, 0, 1))``, in pixels. Skew must be 0.
        width: image width W in pixels.
        height: image height H in pixels.
        dist: OpenCV distortion coefficients in OpenCV order; 0, 4, 5, 8, 12 or 14 values. ``()`` means none.

    Lists are accepted for ``K`` and ``dist`` and stored as tuples of floats, so a camera is hashable and picklable.
    """

    K: tuple[tuple[float, float, float], tuple[float, float, float], tuple[float, float, float]]
    width: int
    height: int
    dist: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, "K", _validate_K(self.K))
        object.__setattr__(self, "dist", _validate_dist(self.dist))
        object.__setattr__(self, "width", _validate_side(self.width, "width"))
        object.__setattr__(self, "height", _validate_side(self.height, "height"))

    @property
    def image_size(self) -> tuple[int, int]:
        """``(H, W)`` in pixels."""
        return (self.height, self.width)

    @property
    def fx(self) -> float:
        return self.K[0][0]

    @property
    def fy(self) -> float:
        return self.K[1][1]

    @property
    def cx(self) -> float:
        return self.K[0][2]

    @property
    def cy(self) -> float:
        return self.K[1][2]

    @property
    def has_distortion(self) -> bool:
        """True when any distortion coefficient is non-zero."""
        return any(d != 0.0 for d in self.dist)

    def K_tensor(self, dtype: torch.dtype = torch.float64, device: torch.device | str | None = None) -> torch.Tensor:
        """``K`` as a ``(3, 3)`` tensor."""
        return torch.tensor(self.K, dtype=dtype, device=device)

    def K_array(self) -> np.ndarray:
        """``K`` as a ``(3, 3)`` float64 array (for OpenCV)."""
        return np.array(self.K, dtype=np.float64)

    def dist_array(self) -> np.ndarray:
        """``dist`` as a ``(D,)`` float64 array (for OpenCV); ``(0,)`` when there is no distortion."""
        return np.array(self.dist, dtype=np.float64)

    def with_image_size(self, image_size: Sequence[int]) -> Camera:
        """This camera resized to ``image_size`` ``(H, W)``; the same as :func:`resize_camera`."""
        return resize_camera(self, image_size)

    def to_dict(self) -> dict:
        """The camera as the JSON file's dict: ``{"K": 3x3 lists, "dist": list, "width": W, "height": H}``."""
        return {"K": [list(row) for row in self.K], "dist": list(self.dist), "width": self.width, "height": self.height}


def camera_from_dict(data: object, source: str = "camera") -> Camera:
    """Build a :class:`Camera` from the JSON file's dict; ``source`` names the origin in error messages.

    ``K``, ``width`` and ``height`` are required, ``dist`` is optional (default none); other keys are an error.
    """
    if not isinstance(data, dict):
        keys = ", ".join(_JSON_KEYS)
        raise ConfigError(f"{source}: expected a JSON object with keys {keys}, got {type(data).__name__}")
    unknown = sorted(set(data) - set(_JSON_KEYS))
    if unknown:
        names = ", ".join(map(repr, unknown))
        raise ConfigError(f"{source}: unknown key(s) {names}; valid keys: {', '.join(_JSON_KEYS)}")
    for key in ("K", "width", "height"):
        if key not in data:
            raise ConfigError(f"{source}: missing key {key!r}; required keys: K, width, height (dist optional)")
    try:
        return Camera(K=data["K"], width=data["width"], height=data["height"], dist=data.get("dist", ()))
    except ConfigError as e:
        raise ConfigError(f"{source}: {e}") from None


def load_camera(path: str | Path) -> Camera:
    """Read a camera JSON file ``{"K": [[fx,0,cx],[0,fy,cy],[0,0,1]], "dist": [...], "width": W, "height": H}``.

    Raises:
        AssetError: the file is missing or unreadable.
        ConfigError: the file is not valid JSON, or a key is missing, unknown or invalid (the message names it).
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise AssetError(f"camera file not found: {path}") from None
    except (OSError, UnicodeDecodeError) as e:
        raise AssetError(f"cannot read camera file {path}: {e}") from None
    try:
        data = json.loads(text)
    except json.JSONDecodeError as e:
        raise ConfigError(f"{path}: not valid JSON ({e.msg} at line {e.lineno} column {e.colno})") from None
    return camera_from_dict(data, source=str(path))


def save_camera(camera: Camera, path: str | Path) -> None:
    """Write ``camera`` as JSON to ``path`` (parent folders are created)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(camera_to_json(camera) + "\n", encoding="utf-8")


def camera_to_json(camera: Camera) -> str:
    """The camera file's text, one key per line (floats written exactly, so a load gives the same camera)."""
    lines = [f"  {json.dumps(key)}: {json.dumps(value)}" for key, value in camera.to_dict().items()]
    return "{\n" + ",\n".join(lines) + "\n}"


def project_points(points_cam: torch.Tensor, K: torch.Tensor, *, min_depth: float = 1e-6) -> torch.Tensor:
    """Project camera-frame points to pixels with a pinhole model (no distortion); differentiable.

    Convention:
        OpenCV camera frame (z forward), metres; pixels ``(u, v)`` = (column, row), pixel centres at integers:
        ``u = fx * x / z + cx``, ``v = fy * y / z + cy``. This equals ``cv2.projectPoints`` with zero distortion.

    Points at or behind the camera (``z <= min_depth``) are projected as if their depth were ``min_depth``: the
    result stays finite (far outside the image for ``x, y != 0``) and the gradient with respect to ``z`` is zero
    there, while ``x`` and ``y`` keep a finite gradient. The clamp is a ``torch.where``, so no NaN leaks into the
    backward pass. Callers that must treat such points as invalid should test ``z`` themselves.

    Args:
        points_cam: ``(B, N, 3)`` points in the camera frame, metres.
        K: ``(3, 3)`` or ``(B, 3, 3)`` intrinsics in pixels, same dtype and device as ``points_cam``.
        min_depth: smallest depth used in the division, metres (> 0).

    Returns:
        ``(B, N, 2)`` pixel coordinates ``(u, v)``.
    """
    dims = check_shape(points_cam, ("B", "N", 3), "points_cam")
    if K.dim() == 2:
        check_shape(K, (3, 3), "K")
    else:
        check_shape(K, (dims["B"], 3, 3), "K")
    if K.dtype != points_cam.dtype or K.device != points_cam.device:
        raise ShapeError(
            f"K: expected dtype {points_cam.dtype} on {points_cam.device} like points_cam, got {K.dtype} on {K.device}"
        )
    check_positive(min_depth, "min_depth")
    z = points_cam[..., 2:3]  # (B, N, 1)
    safe_z = torch.where(z > min_depth, z, torch.full_like(z, min_depth))
    xy_norm = points_cam[..., :2] / safe_z  # (B, N, 2) normalised image coordinates
    return denormalize_points_with_intrinsics(xy_norm, K)


def resize_camera(camera: Camera, image_size: Sequence[int]) -> Camera:
    """The camera that sees the same scene in an image resized to ``image_size`` ``(H', W')``.

    With ``sx = W' / W`` and ``sy = H' / H`` and pixel centres at integers (``u' = (u + 0.5) * sx - 0.5``, as
    ``cv2.resize`` maps pixels): ``fx' = fx * sx``, ``cx' = (cx + 0.5) * sx - 0.5`` and likewise ``fy'``, ``cy'``.
    Distortion acts on normalised coordinates, so ``dist`` is unchanged.
    """
    H2, W2 = check_image_size(image_size)
    sx = W2 / camera.width
    sy = H2 / camera.height
    K = (
        (camera.fx * sx, 0.0, (camera.cx + 0.5) * sx - 0.5),
        (0.0, camera.fy * sy, (camera.cy + 0.5) * sy - 0.5),
        (0.0, 0.0, 1.0),
    )
    return Camera(K=K, width=W2, height=H2, dist=camera.dist)


def working_size(image_size: Sequence[int], max_side: int) -> tuple[int, int]:
    """``(H, W)`` scaled by ``s = max_side / max(H, W)`` when that is < 1, else unchanged.

    Each side is ``max(1, round(side * s))`` (Python ``round``: halves go to the even integer), so the aspect
    ratio is kept to within half a pixel per side; the longest side becomes exactly ``max_side``.
    """
    H, W = check_image_size(image_size)
    max_side = _validate_side(max_side, "max_side")
    s = max_side / max(H, W)
    if s >= 1.0:
        return (H, W)
    return (max(1, round(H * s)), max(1, round(W * s)))


def working_camera(camera: Camera, max_side: int) -> Camera:
    """``camera`` resized (see :func:`resize_camera`) so that its longest side is at most ``max_side`` pixels.

    The size is :func:`working_size`; a camera already small enough is returned unchanged (never enlarged).
    ``K`` uses the exact per-axis factors of the rounded size, so it matches ``resize_image`` to that size.
    """
    size = working_size(camera.image_size, max_side)
    return camera if size == camera.image_size else resize_camera(camera, size)


def check_image_matches_camera(image_hw: Sequence[int], camera: Camera) -> None:
    """Raise ``ConfigError("camera is WxH but image is WxH")`` unless ``image_hw`` ``(H, W)`` is the camera's size."""
    H, W = check_image_size(image_hw, "image size")
    if (H, W) != camera.image_size:
        raise ConfigError(f"camera is {camera.width}x{camera.height} but image is {W}x{H}")


def resize_image(image: np.ndarray, image_size: Sequence[int], *, is_mask: bool) -> np.ndarray:
    """Resize an image or mask to ``image_size`` ``(H', W')`` with OpenCV (pixel-centre convention of this module).

    Images (``(H, W)`` or ``(H, W, C)``, any OpenCV dtype) use ``INTER_AREA``: a box average when shrinking,
    bilinear-like when enlarging. Masks (``(H, W)`` bool) are area-averaged as 0/1 floats and thresholded at
    ``>= 0.5``, so an output pixel is set when at least half of the input area it covers is set; the result is a
    ``(H', W')`` bool array. This keeps thin parts better than nearest-neighbour sampling and has no phase shift.
    """
    H2, W2 = check_image_size(image_size)
    if is_mask:
        _check_mask(image, "mask")
        area = cv2.resize(image.astype(np.float32), (W2, H2), interpolation=cv2.INTER_AREA)
        return area >= 0.5
    _check_image(image, "image")
    return cv2.resize(image, (W2, H2), interpolation=cv2.INTER_AREA)


def undistort_image(image: np.ndarray, camera: Camera, *, is_mask: bool = False) -> tuple[np.ndarray, Camera]:
    """Remove lens distortion; returns the undistorted image and its distortion-free camera.

    The output keeps the image size and the same ``K`` (``cv2.initUndistortRectifyMap`` with
    ``newCameraMatrix = K``), with ``dist = ()``: a pixel of the output sees the ray ``K^-1 (u, v, 1)``. This keeps
    the focal length and principal point the user calibrated; corners that had no source pixel become 0, and
    parts of a strongly distorted image may fall outside. Images are resampled bilinearly, masks (``(H, W)`` bool,
    returned as bool) by nearest neighbour so they stay binary. A camera without distortion returns a copy.

    Args:
        image: ``(H, W)`` or ``(H, W, C)`` array, or an ``(H, W)`` bool mask with ``is_mask=True``; ``(H, W)`` must
            be the camera's size.
        camera: the camera that took ``image``.
    """
    if is_mask:
        _check_mask(image, "mask")
    else:
        _check_image(image, "image")
    check_image_matches_camera(image.shape[:2], camera)
    out_camera = Camera(K=camera.K, width=camera.width, height=camera.height)
    if not camera.has_distortion:
        return image.copy(), out_camera
    K = camera.K_array()
    map_x, map_y = cv2.initUndistortRectifyMap(
        K, camera.dist_array(), None, K, (camera.width, camera.height), cv2.CV_32FC1
    )
    if is_mask:
        out = cv2.remap(image.astype(np.uint8), map_x, map_y, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT)
        return out.astype(bool), out_camera
    out = cv2.remap(image, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    return out, out_camera


def _validate_K(K: object) -> tuple[tuple[float, float, float], ...]:
    want = "K: expected a 3x3 matrix [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]"
    try:
        rows = tuple(tuple(float(v) for v in row) for row in K)  # type: ignore[union-attr]
    except (TypeError, ValueError):
        raise ConfigError(f"{want}, got {K!r}") from None
    if len(rows) != 3 or any(len(r) != 3 for r in rows):
        raise ConfigError(f"{want}, got {K!r}")
    if not all(math.isfinite(v) for r in rows for v in r):
        raise ConfigError(f"{want} of finite numbers, got {K!r}")
    if rows[2] != (0.0, 0.0, 1.0):
        raise ConfigError(f"K: expected the last row to be [0, 0, 1], got {list(rows[2])}")
    if rows[0][1] != 0.0 or rows[1][0] != 0.0:
        raise ConfigError(f"K: expected K[0][1] = K[1][0] = 0 (skew is not supported), got {rows[0][1]}, {rows[1][0]}")
    if rows[0][0] <= 0 or rows[1][1] <= 0:
        raise ConfigError(
            f"K: expected focal lengths fx = K[0][0] > 0 and fy = K[1][1] > 0, got {rows[0][0]}, {rows[1][1]}"
        )
    return rows


def _validate_dist(dist: object) -> tuple[float, ...]:
    try:
        values = tuple(float(v) for v in dist)  # type: ignore[union-attr]
    except (TypeError, ValueError):
        raise ConfigError(f"dist: expected a list of numbers (OpenCV order), got {dist!r}") from None
    if len(values) not in DIST_COUNTS:
        raise ConfigError(
            f"dist: expected {', '.join(map(str, DIST_COUNTS))} coefficients (OpenCV order), got {len(values)}"
        )
    if not all(math.isfinite(v) for v in values):
        raise ConfigError(f"dist: expected finite numbers, got {list(values)}")
    return values


def _validate_side(value: object, name: str) -> int:
    try:
        if isinstance(value, bool):
            raise TypeError
        side = operator.index(value)  # type: ignore[arg-type]
    except TypeError:
        raise ConfigError(f"{name}: expected a positive int, got {value!r}") from None
    if side <= 0:
        raise ConfigError(f"{name}: expected a positive int, got {value!r}")
    return side


def _check_image(image: object, name: str) -> None:
    if not isinstance(image, np.ndarray) or image.ndim not in (2, 3) or image.dtype == bool:
        got = f"{image.dtype} {image.shape}" if isinstance(image, np.ndarray) else type(image).__name__
        raise ShapeError(f"{name}: expected an (H, W) or (H, W, C) numeric array, got {got}")


def _check_mask(mask: object, name: str) -> None:
    if not isinstance(mask, np.ndarray) or mask.ndim != 2 or mask.dtype != bool:
        got = f"{mask.dtype} {mask.shape}" if isinstance(mask, np.ndarray) else type(mask).__name__
        raise ShapeError(f"{name}: expected an (H, W) bool array, got {got}")
