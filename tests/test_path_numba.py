"""The compiled model path (``pipeline._path_numba.PathPoints``) against its torch operations
(``shape_estimation._path_points_torch``): values, gradients, and a finite-difference check."""

import numpy as np
import torch

from pipeline._path_numba import PathPoints
from pipeline.shape_estimation import _path_points_torch

F64 = torch.float64
BOUNDS = (0.0, 0.0, 100.0, 80.0)


def paths(S=5, R=12, A=8, C=2, seed=0):
    """``S`` wavy projected paths ``(S, R, 2)`` pixels (the second partly left of the image, so some of its segments
    do not count), end rings ``(S, 2, A, 2)`` around their ends, per-ring attributes ``(S, R, C)``."""
    g = torch.Generator().manual_seed(seed)
    centre = torch.cumsum(torch.rand(S, R, 2, generator=g, dtype=F64) * 10 + 2, dim=1)
    centre[1] -= 40
    rings = centre[:, [0, -1]][:, :, None] + 6 * torch.randn(S, 2, A, 2, generator=g, dtype=F64)
    rings[2, 0] = centre[2, 0] + 0.1 * (centre[2, 1] - centre[2, 0])  # a base ring wholly inwards: the cap stays
    return centre, rings, torch.rand(S, R, C, generator=g, dtype=F64)


def test_path_points_equal_the_torch_operations():
    """Points and attributes at fractions of the visible length (0 and 1 included: the path's ends), and the
    gradients of a weighted sum of both with respect to the centres, the end rings and the attributes: to 1e-12."""
    centre, rings, attributes = paths()
    fractions = torch.tensor([0.0, 0.1, 0.25, 0.5, 0.77, 0.99, 1.0], dtype=F64)
    g = torch.Generator().manual_seed(1)
    w_points, w_attributes = torch.randn(5, 7, 2, generator=g, dtype=F64), torch.randn(5, 7, 2, generator=g, dtype=F64)
    results = []
    for compiled in (True, False):
        inputs = [v.clone().requires_grad_() for v in (centre, rings, attributes)]
        if compiled:
            located, at = PathPoints.apply(*inputs, np.asarray(BOUNDS), fractions.numpy())
        else:
            located, at = _path_points_torch(inputs[0], inputs[1], BOUNDS, fractions, inputs[2])
        ((located * w_points).sum() + (at * w_attributes).sum()).backward()
        results.append([located.detach(), at.detach()] + [v.grad for v in inputs])
    for a, b in zip(*results):
        assert torch.isfinite(a).all()
        torch.testing.assert_close(a, b, atol=1e-12, rtol=0)
    assert results[0][3][2, 0].abs().max() == 0  # the inward base ring does not move the cap: no gradient


def test_gradcheck_path_points():
    centre, rings, attributes = paths(S=3, R=6, A=5, C=1, seed=2)
    fractions = np.array([0.2, 0.5, 0.9])

    def f(c, r, a):
        located, at = PathPoints.apply(c, r, a, np.asarray(BOUNDS), fractions)
        return torch.cat([located.flatten(), at.flatten()])

    assert torch.autograd.gradcheck(f, [v.clone().requires_grad_() for v in (centre, rings, attributes)])
