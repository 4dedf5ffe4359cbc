"""Losses against naive loops; gradients finite at zero distance."""

import numpy as np
import pytest
import torch

from pipeline.errors import ShapeError
from pipeline.losses import appearance_loss, distance_loss, keypoint_loss, mask_loss


def test_losses_match_naive_loops():
    g = torch.Generator().manual_seed(0)
    S = torch.rand(2, 5, 7, generator=g, dtype=torch.float64)
    M = (torch.rand(5, 7, generator=g) > 0.5).double()
    D = torch.rand(5, 7, generator=g, dtype=torch.float64)
    for b in range(2):
        naive_mask = sum((S[b, i, j] - M[i, j]) ** 2 for i in range(5) for j in range(7))
        naive_dist = sum(S[b, i, j] * D[i, j] for i in range(5) for j in range(7))
        assert float(mask_loss(S, M)[b]) == pytest.approx(float(naive_mask))
        naive_weighted = sum(D[i, j] * (S[b, i, j] - M[i, j]) ** 2 for i in range(5) for j in range(7))
        assert float(mask_loss(S, M, D)[b]) == pytest.approx(float(naive_weighted))
        assert float(distance_loss(S, D)[b]) == pytest.approx(float(naive_dist))
        assert float(appearance_loss(S, M)[b]) == pytest.approx(abs(float(S[b].sum() - M.sum())), abs=1e-8)
    pts = torch.rand(2, 3, 2, generator=g, dtype=torch.float64) * 10
    tgt = torch.rand(3, 2, generator=g, dtype=torch.float64) * 10
    naive = [sum(np.hypot(*(pts[b, k] - tgt[k]).numpy()) for k in range(3)) for b in range(2)]
    np.testing.assert_allclose(keypoint_loss(pts, tgt).numpy(), naive, rtol=1e-9)


def test_keypoint_loss_gradient_finite_at_zero_distance():
    pts = torch.zeros(1, 2, 2, dtype=torch.float64, requires_grad=True)
    keypoint_loss(pts, torch.zeros(2, 2, dtype=torch.float64)).sum().backward()
    assert torch.isfinite(pts.grad).all()
    S = torch.full((1, 2, 2), 0.5, dtype=torch.float64, requires_grad=True)
    appearance_loss(S, torch.tensor([[1.0, 1.0], [0.0, 0.0]], dtype=torch.float64)).sum().backward()
    assert torch.isfinite(S.grad).all()


def test_shape_errors():
    with pytest.raises(ShapeError, match="target"):
        mask_loss(torch.zeros(1, 4, 4), torch.zeros(4, 5))
    with pytest.raises(ShapeError, match="targets_px"):
        keypoint_loss(torch.zeros(1, 3, 2), torch.zeros(4, 2))


def _tensor_mask_loss(S, M, W=None):  # the formula in tensor operations (losses.mask_loss before its CPU pass)
    squared = (S - M) ** 2
    return (squared if W is None else squared * W).sum(dim=(-2, -1))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("batched_mask", [False, True])
@pytest.mark.parametrize("weighted", [False, True])
def test_mask_loss_compiled_pass_matches_the_tensor_formula(dtype, batched_mask, weighted):
    g = torch.Generator().manual_seed(3)
    B, H, W = 3, 17, 23
    S = torch.rand(B, H, W, generator=g, dtype=dtype)
    S[:, :, :9] = 0.0  # empty columns, as a silhouette has
    M = (torch.rand((B, H, W) if batched_mask else (H, W), generator=g) > 0.6).to(dtype)
    D = torch.rand((H, W) if batched_mask else (B, H, W), generator=g, dtype=dtype) if weighted else None
    fast_s, ref_s = S.clone().requires_grad_(True), S.clone().requires_grad_(True)
    fast = mask_loss(fast_s, M, D)
    ref = _tensor_mask_loss(ref_s, M, D)
    assert fast.dtype == dtype and fast.shape == (B,)
    torch.testing.assert_close(fast, ref, rtol=1e-5 if dtype == torch.float32 else 1e-12, atol=0)
    grad_out = torch.tensor([1.0, -2.0, 0.5], dtype=dtype)
    (fast * grad_out).sum().backward()
    (ref * grad_out).sum().backward()
    assert fast_s.grad.dtype == dtype
    torch.testing.assert_close(fast_s.grad, ref_s.grad, rtol=1e-6, atol=1e-6)
    if dtype == torch.float64:
        assert torch.autograd.gradcheck(lambda s: mask_loss(s, M, D), (S.clone().requires_grad_(True),))


def test_mask_loss_with_a_differentiable_target_keeps_the_tensor_formula():
    S = torch.rand(2, 4, 5, dtype=torch.float64, requires_grad=True)
    M = torch.rand(4, 5, dtype=torch.float64, requires_grad=True)
    mask_loss(S, M).sum().backward()
    torch.testing.assert_close(M.grad, -2.0 * (S - M).sum(0).detach())


def test_numba_path_takes_cpu_float_tensors_only():
    """``checks.numba_path``, the one test every numba kernel's caller makes: CPU float32 / float64 tensors, all of
    them, outside ``torch.compile``."""
    from pipeline.checks import numba_path

    assert numba_path(torch.zeros(2), torch.zeros(2, dtype=torch.float64))
    assert not numba_path(torch.zeros(2), torch.zeros(2, dtype=torch.float16))
    assert not numba_path(torch.zeros(2, dtype=torch.int64))
    assert not torch.compile(lambda x: x + float(numba_path(x)), backend="eager")(torch.zeros(1)).item()
