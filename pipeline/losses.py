"""Silhouette and keypoint losses (DESIGN.md section 1). Pure tensor functions, batch-first, one value per image.

These are the raw sums of the method's equations; the estimators normalise them (by the mask area, the image
size) so that their default weights hold at any resolution, and say how in their docstrings and ``docs/method.md``.
"""

from __future__ import annotations

import torch

from pipeline.checks import check_shape, numba_path


def mask_loss(silhouette: torch.Tensor, mask: torch.Tensor, weight: torch.Tensor | None = None) -> torch.Tensor:
    """``L_mask = sum_px W (S - M)^2`` (``W`` = 1 by default).

    Args:
        silhouette: (B, H, W) soft silhouette in [0, 1].
        mask: (H, W) or (B, H, W) target mask in {0, 1} (float).
        weight: (H, W) or (B, H, W) per-pixel weights, or ``None`` for ones.

    Returns:
        (B,) per-image loss, squared-pixel units.
    """
    _check_pair(silhouette, mask)
    if weight is not None:
        _check_pair(silhouette, weight)
    if _compiled_pass(silhouette, mask, weight):
        from pipeline._losses_numba import MaskLossNumba

        return MaskLossNumba.apply(silhouette, mask, weight)
    squared = (silhouette - mask) ** 2
    if weight is not None:
        squared = squared * weight
    return squared.sum(dim=(-2, -1))


def _compiled_pass(silhouette: torch.Tensor, *targets: torch.Tensor | None) -> bool:
    """Whether ``mask_loss`` runs as one compiled pass (``pipeline._losses_numba``): CPU float tensors whose targets
    need no gradient, outside ``torch.compile``'s tracing (which keeps the tensor formula)."""
    tensors = [silhouette] + [t for t in targets if t is not None]
    return numba_path(*tensors) and not any(t.requires_grad for t in tensors[1:])


def distance_loss(silhouette: torch.Tensor, distance_map: torch.Tensor) -> torch.Tensor:
    """``L_dist = sum_px S * D``, with ``D`` zero inside the mask and ``distance_to_mask / gamma`` outside.

    Args:
        silhouette: (B, H, W).
        distance_map: (H, W) or (B, H, W) the already-scaled ``D``.

    Returns:
        (B,) per-image loss.
    """
    _check_pair(silhouette, distance_map)
    return (silhouette * distance_map).sum(dim=(-2, -1))


def appearance_loss(silhouette: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """``L_app = | sum_px S - sum_px M |``: keeps the rendered area right, so depth does not drift.

    Returns:
        (B,) per-image loss, pixels.
    """
    _check_pair(silhouette, mask)
    diff = silhouette.sum(dim=(-2, -1)) - mask.sum(dim=(-2, -1))
    return _smooth_abs(diff)


def keypoint_loss(points_px: torch.Tensor, targets_px: torch.Tensor) -> torch.Tensor:
    """``L_kp = sum_k | pi(p(s_k)) - x_k |`` (Euclidean pixel distances).

    Args:
        points_px: (B, K, 2) projected model points (u, v).
        targets_px: (K, 2) or (B, K, 2) observed keypoints (u, v).

    Returns:
        (B,) per-image sum of distances, pixels. Smooth at zero distance (no NaN gradient).
    """
    dims = check_shape(points_px, ("B", "K", 2), "points_px")
    if targets_px.dim() == 2:
        check_shape(targets_px, (dims["K"], 2), "targets_px")
    else:
        check_shape(targets_px, (dims["B"], dims["K"], 2), "targets_px")
    return _smooth_abs(points_px - targets_px, dim=-1).sum(dim=-1)


def _smooth_abs(x: torch.Tensor, dim: int | None = None, eps: float = 1e-9) -> torch.Tensor:
    """|x| (or the Euclidean norm over ``dim``) as sqrt(x^2 + eps^2): differentiable at zero."""
    squared = x * x if dim is None else (x * x).sum(dim=dim)
    return torch.sqrt(squared + eps * eps)


def _check_pair(silhouette: torch.Tensor, target: torch.Tensor) -> None:
    dims = check_shape(silhouette, ("B", "H", "W"), "silhouette")
    if target.dim() == 2:
        check_shape(target, (dims["H"], dims["W"]), "target")
    else:
        check_shape(target, (dims["B"], dims["H"], dims["W"]), "target")
