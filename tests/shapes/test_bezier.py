import pytest
import torch

from pipeline.errors import ConfigError, ShapeError
from pipeline.shapes.bezier import bernstein_basis, bezier_derivative, bezier_points, elevate_bezier_degree


def de_casteljau(control_points, s):
    """Naive reference: repeated linear interpolation, one s at a time."""
    out = []
    for b in range(control_points.shape[0]):
        row = []
        for sv in s.tolist():
            pts = [control_points[b, i] for i in range(control_points.shape[1])]
            while len(pts) > 1:
                pts = [(1 - sv) * pts[i] + sv * pts[i + 1] for i in range(len(pts) - 1)]
            row.append(pts[0])
        out.append(torch.stack(row))
    return torch.stack(out)


def random_cp(B, n, seed=0, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    return torch.randn(B, n + 1, 3, generator=g, dtype=dtype)


@pytest.mark.parametrize("n", [1, 2, 3, 5])
@pytest.mark.parametrize("B", [1, 3])
def test_points_match_de_casteljau(n, B):
    cp = random_cp(B, n, seed=n)
    s = torch.linspace(0, 1, 17, dtype=torch.float64)
    p = bezier_points(cp, s)
    assert p.shape == (B, 17, 3)
    torch.testing.assert_close(p, de_casteljau(cp, s))
    torch.testing.assert_close(p[:, 0], cp[:, 0])
    torch.testing.assert_close(p[:, -1], cp[:, -1])


def test_basis_partition_of_unity():
    s = torch.linspace(0, 1, 11)
    torch.testing.assert_close(bernstein_basis(4, s).sum(-1), torch.ones(11))


@pytest.mark.parametrize("n", [0, 1, 2, 3, 6])
def test_basis_matches_pascals_triangle(n):
    """``b_{i,n}(s) = binom(n, i) (1-s)^(n-i) s^i`` with the binomials built row by row (Pascal's rule), not
    by the library's ``math.comb``."""
    row = [1]
    for _ in range(n):
        row = [a + b for a, b in zip([0] + row, row + [0])]
    s = torch.tensor([0.0, 0.2, 0.5, 0.9, 1.0], dtype=torch.float64)
    expected = torch.stack([row[i] * (1 - s) ** (n - i) * s**i for i in range(n + 1)], -1)
    torch.testing.assert_close(bernstein_basis(n, s), expected, atol=1e-15, rtol=0)


@pytest.mark.parametrize("n", [1, 2, 3, 4])
def test_derivatives_match_finite_differences(n):
    cp = random_cp(2, n, seed=10 + n)
    s = torch.linspace(0.05, 0.95, 9, dtype=torch.float64)
    h = 1e-5
    fd1 = (bezier_points(cp, s + h) - bezier_points(cp, s - h)) / (2 * h)
    fd2 = (bezier_points(cp, s + h) - 2 * bezier_points(cp, s) + bezier_points(cp, s - h)) / h**2
    torch.testing.assert_close(bezier_derivative(cp, s, 1), fd1, atol=1e-7, rtol=1e-7)
    torch.testing.assert_close(bezier_derivative(cp, s, 2), fd2, atol=1e-3, rtol=1e-4)


def test_quadratic_formulas_of_the_paper():
    cp = random_cp(2, 2, seed=3)
    c0, c1, c2 = cp[:, 0:1], cp[:, 1:2], cp[:, 2:3]
    s = torch.linspace(0, 1, 7, dtype=torch.float64)[None, :, None]
    d1 = 2 * (1 - s) * (c1 - c0) + 2 * s * (c2 - c1)
    d2 = (2 * (c2 - 2 * c1 + c0)).expand(-1, 7, -1)
    torch.testing.assert_close(bezier_derivative(cp, s[0, :, 0], 1), d1)
    torch.testing.assert_close(bezier_derivative(cp, s[0, :, 0], 2), d2)


def test_derivative_above_order_is_zero_and_connected():
    cp = random_cp(2, 1).requires_grad_()
    s = torch.linspace(0, 1, 5, dtype=torch.float64)
    d2 = bezier_derivative(cp, s, 2)
    assert d2.shape == (2, 5, 3) and not d2.any()
    (grad,) = torch.autograd.grad(d2.sum(), cp)
    assert not grad.any()


def test_dtype_follows_input():
    cp = random_cp(1, 2, dtype=torch.float32)
    s = torch.linspace(0, 1, 4)
    assert bezier_points(cp, s).dtype == torch.float32
    assert bezier_derivative(cp, s, 1).dtype == torch.float32


def test_gradcheck():
    cp = random_cp(2, 3).requires_grad_()
    s = torch.tensor([0.0, 0.3, 1.0], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda c, t: bezier_points(c, t), (cp, s))
    assert torch.autograd.gradcheck(lambda c, t: bezier_derivative(c, t, 1), (cp, s))
    assert torch.autograd.gradcheck(lambda c, t: bezier_derivative(c, t, 2), (cp, s))


def test_errors():
    s = torch.linspace(0, 1, 3)
    with pytest.raises(ShapeError, match="at least 2 control points"):
        bezier_points(torch.zeros(1, 1, 3), s)
    with pytest.raises(ShapeError, match=r"expected shape \(B, \*, \*\)"):
        bezier_points(torch.zeros(3, 3), s)
    with pytest.raises(ShapeError, match="dtype"):
        bezier_points(torch.zeros(1, 3, 3, dtype=torch.float64), s)
    with pytest.raises(ConfigError, match="derivative order"):
        bezier_derivative(torch.zeros(1, 3, 3), s, 0)
    with pytest.raises(ConfigError, match="Bernstein degree"):
        bernstein_basis(-1, s)


@pytest.mark.parametrize("n,degrees", [(1, 1), (2, 1), (2, 3), (4, 1)])
def test_degree_elevation_is_the_same_curve(n, degrees):
    """Against the naive de Casteljau evaluation of the original control points."""
    cp = random_cp(2, n, seed=10 + n)
    up = elevate_bezier_degree(cp, degrees)
    assert up.shape == (2, n + 1 + degrees, 3)
    s = torch.linspace(0, 1, 23, dtype=torch.float64)
    torch.testing.assert_close(bezier_points(up, s), de_casteljau(cp, s))
    torch.testing.assert_close(elevate_bezier_degree(cp, 0), cp)
    with pytest.raises(ConfigError, match="degrees"):
        elevate_bezier_degree(cp, -1)
