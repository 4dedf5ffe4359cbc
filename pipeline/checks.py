"""Shape and value checks that raise clear errors (never ``assert``, which vanishes under ``-O``)."""

from __future__ import annotations

from collections.abc import Sequence

import torch

from pipeline.errors import ConfigError, ShapeError


# No dependency checks shapes (jaxtyping is not one): this binds named sizes across arguments, says what came.
def check_shape(x: torch.Tensor, spec: Sequence[int | str | None], name: str) -> dict[str, int]:
    """Check ``x.shape`` against ``spec`` and return the sizes bound to named dimensions.

    ``spec`` holds ints (exact size), strings (a named size, equal wherever the name recurs) or ``None`` (any).
    Example: ``check_shape(verts, ("B", "V", 3), "verts")`` accepts ``(2, 10, 3)`` and returns ``{"B": 2, "V": 10}``.
    """
    if not isinstance(x, torch.Tensor):
        raise ShapeError(f"{name}: expected a torch.Tensor of shape {_fmt(spec)}, got {type(x).__name__}")
    if x.dim() != len(spec):
        raise ShapeError(f"{name}: expected shape {_fmt(spec)}, got {tuple(x.shape)}")
    bound: dict[str, int] = {}
    for size, want in zip(x.shape, spec):
        if want is None:
            continue
        if isinstance(want, str):
            if bound.setdefault(want, size) != size:
                raise ShapeError(f"{name}: expected shape {_fmt(spec)}, got {tuple(x.shape)} ({want} differs)")
        elif size != want:
            raise ShapeError(f"{name}: expected shape {_fmt(spec)}, got {tuple(x.shape)}")
    return bound


def check_finite(x: torch.Tensor, name: str) -> None:
    """Raise if ``x`` holds NaN or inf."""
    if not bool(torch.isfinite(x).all()):
        raise ShapeError(f"{name}: contains NaN or inf")


def check_image_size(image_size: Sequence[int], name: str = "image_size") -> tuple[int, int]:
    """Validate an ``(H, W)`` pair of positive ints and return it as a tuple."""
    try:
        H, W = (int(s) for s in image_size)
    except (TypeError, ValueError):
        raise ConfigError(f"{name}: expected (H, W), two positive ints, got {image_size!r}") from None
    if H <= 0 or W <= 0 or (H, W) != tuple(image_size):
        raise ConfigError(f"{name}: expected (H, W), two positive ints, got {image_size!r}")
    return H, W


def check_choice(value: str, choices: Sequence[str], name: str) -> str:
    """Raise a ``ConfigError`` listing ``choices`` unless ``value`` is one of them."""
    if value not in choices:
        raise ConfigError(f"{name}: expected one of {', '.join(map(repr, choices))}, got {value!r}")
    return value


def check_positive(value: float, name: str, *, allow_zero: bool = False) -> float:
    """Raise unless ``value`` is a finite number > 0 (>= 0 with ``allow_zero``)."""
    v = float(value)
    ok = v >= 0 if allow_zero else v > 0
    if not ok or v != v or v in (float("inf"), float("-inf")):
        raise ConfigError(f"{name}: expected a finite number {'>= 0' if allow_zero else '> 0'}, got {value!r}")
    return v


def numba_path(*tensors: torch.Tensor) -> bool:
    """Whether the numba kernels (the rasterizer's, the mask loss's, the shape fit's) take these tensors: all on the
    CPU, float32 or float64, and not inside ``torch.compile``'s tracing (which keeps the torch operations)."""
    return (all(t.device.type == "cpu" and t.dtype in (torch.float32, torch.float64) for t in tensors)
            and not torch.compiler.is_compiling())


def _fmt(spec: Sequence[int | str | None]) -> str:
    return "(" + ", ".join("*" if s is None else str(s) for s in spec) + ")"
