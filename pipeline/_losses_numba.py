"""CPU mask loss: ``sum_px W (S - M)^2`` and its gradient as one compiled pass each (``losses.mask_loss`` uses it
for CPU tensors).

In tensor operations the loss is a subtraction, a square and a sum forward and three more image-sized passes
backward, each allocating an image batch: 2.4 ms a call for a warm tracking batch's 18 silhouettes of 202 x 231
pixels (one thread), where one pass reading the two images takes 0.2 ms (``docs/renderer.md``). Rows run in
parallel; each row's sum is accumulated in float64 and the rows of an image are added in order, so the value does
not depend on the thread count. Same values as the tensor formula to float rounding.
"""

from __future__ import annotations

import numba as nb
import numpy as np
import torch
from torch.autograd.function import once_differentiable

_JIT = dict(cache=True, nogil=True, fastmath=False)


@nb.njit(parallel=True, **_JIT)
def _forward(s, m, w, weighted, out):
    """``out[b] = sum_ij w (s[b] - m)^2``; ``m`` and ``w`` are ``(1 or B, H, W)`` (``w`` unread unless
    ``weighted``)."""
    B, H, W = s.shape
    rows = np.empty(B * H)
    for r in nb.prange(B * H):
        b = r // H
        i = r - b * H
        mb = b if m.shape[0] > 1 else 0
        wb = b if w.shape[0] > 1 else 0
        acc = 0.0
        for j in range(W):
            d = float(s[b, i, j]) - float(m[mb, i, j])
            acc += d * d * float(w[wb, i, j]) if weighted else d * d
        rows[r] = acc
    for b in range(B):
        total = 0.0
        for i in range(H):
            total += rows[b * H + i]
        out[b] = total


@nb.njit(parallel=True, **_JIT)
def _backward(s, m, w, weighted, grad, out):
    """``out[b] = 2 grad[b] w (s[b] - m)``, the gradient with respect to ``s``."""
    B, H, W = s.shape
    for r in nb.prange(B * H):
        b = r // H
        i = r - b * H
        mb = b if m.shape[0] > 1 else 0
        wb = b if w.shape[0] > 1 else 0
        c = 2.0 * grad[b]
        for j in range(W):
            d = float(s[b, i, j]) - float(m[mb, i, j])
            out[b, i, j] = c * d * float(w[wb, i, j]) if weighted else c * d


def _batched(x: torch.Tensor) -> np.ndarray:
    """``(H, W)`` or ``(B, H, W)`` -> a contiguous ``(1 or B, H, W)`` array (no copy where it already is one)."""
    return x.detach().reshape(-1, *x.shape[-2:]).contiguous().numpy()


class MaskLossNumba(torch.autograd.Function):
    """silhouette (B, H, W), mask and weight (H, W) or (B, H, W) (weight ``None``: ones) -> (B,) in the
    silhouette's dtype; gradient with respect to the silhouette only."""

    @staticmethod
    def forward(ctx, silhouette, mask, weight):
        s = silhouette.detach().contiguous().numpy()
        m = _batched(mask)
        w = _batched(weight) if weight is not None else np.ones((1, 1, 1), s.dtype)
        out = np.empty(s.shape[0])
        _forward(s, m, w, weight is not None, out)
        ctx.saved = (s, m, w, weight is not None)
        return torch.from_numpy(out).to(silhouette.dtype)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad):
        s, m, w, weighted = ctx.saved
        out = np.empty_like(s)
        _backward(s, m, w, weighted, grad.detach().to(torch.float64).contiguous().numpy(), out)
        return torch.from_numpy(out), None, None
