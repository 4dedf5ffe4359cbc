import pytest
import torch

from pipeline.errors import ConfigError, ShapeError
from pipeline.shapes.bezier import bezier_derivative, bezier_points
from pipeline.shapes.frames import (
    _bezier_frames_torch,
    _rmf_torch,
    bezier_frames,
    bezier_weights,
    frenet_frames,
    initial_normal,
    rotation_minimizing_frames,
)

F64 = torch.float64


def assert_orthonormal_right_handed(frames, atol=1e-10):
    t, n, b = frames
    for v in (t, n, b):
        torch.testing.assert_close(v.norm(dim=-1), torch.ones(v.shape[:-1], dtype=v.dtype), atol=atol, rtol=0)
    for u, v in ((t, n), (t, b), (n, b)):
        assert (u * v).sum(-1).abs().max() < atol
    torch.testing.assert_close(torch.linalg.cross(t, n, dim=-1), b, atol=atol, rtol=0)


def planar_quadratic():
    return torch.tensor([[[0.0, 0.0, 0.4], [0.1, 0.0, 0.45], [0.15, 0.08, 0.4]]], dtype=F64)


def s_shaped_cubic():
    return torch.tensor([[[0.0, 0.0, 0.5], [0.1, 0.1, 0.5], [0.2, -0.1, 0.5], [0.3, 0.0, 0.5]]], dtype=F64)


def straight():
    return torch.tensor([[[0.0, 0.0, 0.3], [0.05, 0.05, 0.35], [0.1, 0.1, 0.4]]], dtype=F64)


def twisted_cubic():
    """Non-planar: the control points do not lie in one plane, so the curve has torsion."""
    return torch.tensor([[[0.0, 0.0, 0.4], [0.1, 0.08, 0.5], [0.2, -0.1, 0.33], [0.3, 0.06, 0.47]]], dtype=F64)


def naive_double_reflection(points, tangents, normal_start):
    """Reference RMF: the double-reflection method (Wang et al. 2008, algorithm 1) one step at a time in a loop,
    for a single curve ``(S, 3)``."""
    t = tangents / tangents.norm(dim=-1, keepdim=True)
    r = [normal_start]
    for i in range(len(points) - 1):
        v1 = points[i + 1] - points[i]
        c1 = v1 @ v1
        r_left = r[i] - (2 / c1) * (v1 @ r[i]) * v1
        t_left = t[i] - (2 / c1) * (v1 @ t[i]) * v1
        v2 = t[i + 1] - t_left
        c2 = v2 @ v2
        r.append(r_left - (2 / c2) * (v2 @ r_left) * v2)
    return torch.stack(r)


def test_frenet_matches_definition():
    cp = planar_quadratic()
    s = torch.linspace(0, 1, 20, dtype=F64)
    d1, d2 = bezier_derivative(cp, s, 1), bezier_derivative(cp, s, 2)
    frames = frenet_frames(d1, d2)
    assert_orthonormal_right_handed(frames)
    torch.testing.assert_close(frames.tangent, d1 / d1.norm(dim=-1, keepdim=True))
    cross = torch.linalg.cross(d1, d2, dim=-1)
    torch.testing.assert_close(frames.binormal, cross / cross.norm(dim=-1, keepdim=True))
    torch.testing.assert_close(frames.normal, torch.linalg.cross(frames.binormal, frames.tangent, dim=-1))


@pytest.mark.parametrize("cp", [straight(), s_shaped_cubic()])
def test_frenet_raises_where_undefined(cp):
    s = torch.linspace(0, 1, 21, dtype=F64)  # the cubic inflects at s = 0.5
    with pytest.raises(ShapeError, match="Frenet frame undefined"):
        bezier_frames(cp, s, "frenet")


def test_unknown_method():
    with pytest.raises(ConfigError, match="'rmf', 'frenet'"):
        bezier_frames(planar_quadratic(), torch.linspace(0, 1, 3, dtype=F64), "bishop")


@pytest.mark.parametrize("cp", [planar_quadratic(), s_shaped_cubic(), straight(), twisted_cubic()])
def test_rmf_orthonormal_and_twist_free(cp):
    """Orthonormal frames whose normal does not turn about the tangent, on plane curves and a twisted cubic (on a
    plane curve a fixed normal projected onto each normal plane is twist-free too; on the twisted cubic it is not),
    and the same normals as a step-by-step double-reflection loop."""
    s = torch.linspace(0, 1, 100, dtype=F64)
    points, frames = bezier_frames(cp, s, "rmf")
    assert all(torch.isfinite(v).all() for v in frames)
    assert_orthonormal_right_handed(frames)
    # Rotation-minimising: the normal does not turn about the tangent, so N_{i+1} . B_i stays O(step^2).
    twist = (frames.normal[:, 1:] * frames.binormal[:, :-1]).sum(-1).abs().max()
    assert twist < 1e-3
    reference = naive_double_reflection(points[0], bezier_derivative(cp, s, 1)[0], frames.normal[0, 0])
    torch.testing.assert_close(frames.normal[0], reference, atol=1e-10, rtol=0)


def test_rmf_of_a_helix_is_the_analytic_one():
    """On a helix (constant curvature and torsion tau) the RMF normal turns against the Frenet normal at the rate
    -tau per unit arc length: U(s) = cos(tau s) N(s) - sin(tau s) B(s) when both start equal. Two turns, 200 samples;
    the double reflection is fourth-order accurate, so the error stays far below the twist of a wrong frame
    (tau * arc length = 4.7 rad here)."""
    a, b = 0.05, 0.02  # radius and pitch / (2 pi), metres
    c = (a * a + b * b) ** 0.5
    theta = torch.linspace(0, 4 * torch.pi, 200, dtype=F64)
    cos, sin = theta.cos(), theta.sin()
    points = torch.stack([a * cos, a * sin, b * theta + 0.4], -1)[None]
    tangent = torch.stack([-a * sin, a * cos, torch.full_like(theta, b)], -1) / c
    normal = torch.stack([-cos, -sin, torch.zeros_like(theta)], -1)  # Frenet, towards the axis
    binormal = torch.linalg.cross(tangent, normal, dim=-1)
    frames = rotation_minimizing_frames(points, tangent[None], normal[None, 0])
    assert_orthonormal_right_handed(frames)
    phi = (b / c**2) * (c * theta)  # tau * arc length
    expected = phi.cos()[:, None] * normal - phi.sin()[:, None] * binormal
    assert float(phi[-1]) > 4.5  # the Frenet frame (or a fixed one) would be far off
    torch.testing.assert_close(frames.normal[0], expected, atol=1e-6, rtol=0)  # measured 1.2e-8
    twist = (frames.normal[:, 1:] * frames.binormal[:, :-1]).sum(-1).abs().max()
    assert twist < 1e-3


def test_rmf_equals_frenet_up_to_constant_rotation_on_planar_curve():
    cp = planar_quadratic()
    s = torch.linspace(0, 1, 200, dtype=F64)
    _, rmf = bezier_frames(cp, s, "rmf")
    _, fre = bezier_frames(cp, s, "frenet")
    torch.testing.assert_close(rmf.tangent, fre.tangent)
    # For a plane curve the Frenet frame is itself rotation-minimising: the angle between N's is constant.
    cos = (rmf.normal * fre.normal).sum(-1)
    sin = (rmf.normal * fre.binormal).sum(-1)
    angle = torch.atan2(sin, cos)
    assert (angle - angle[:, :1]).abs().max() < 1e-3
    # Seeded by the Frenet normal at s = 0, the constant angle is 0.
    assert angle.abs().max() < 1e-3


def test_rmf_on_straight_line_is_constant_and_grads_finite():
    cp = straight().requires_grad_()
    s = torch.linspace(0, 1, 50, dtype=F64)
    _, frames = bezier_frames(cp, s, "rmf")
    torch.testing.assert_close(frames.normal, frames.normal[:, :1].expand_as(frames.normal))
    for field in frames:
        (grad,) = torch.autograd.grad(field.sum(), cp, retain_graph=True)
        assert torch.isfinite(grad).all()


def test_initial_normal_fallback_axis():
    d1 = torch.tensor([[0.0, 0.0, 2.0], [1.0, 1.0, 0.0]], dtype=F64)
    n = initial_normal(d1, torch.zeros_like(d1))
    torch.testing.assert_close(n[0], torch.tensor([1.0, 0.0, 0.0], dtype=F64))  # first least-aligned axis
    torch.testing.assert_close(n[1], torch.tensor([0.0, 0.0, 1.0], dtype=F64))
    assert (n * d1).sum(-1).abs().max() < 1e-12


def test_batch_and_dtype():
    cp = torch.cat([planar_quadratic(), straight(), planar_quadratic().flip(1)]).float()
    points, frames = bezier_frames(cp, torch.linspace(0, 1, 10), "rmf")
    assert points.shape == (3, 10, 3) and frames.normal.shape == (3, 10, 3)
    assert frames.normal.dtype == torch.float32
    single = bezier_frames(cp[1:2], torch.linspace(0, 1, 10), "rmf")[1]
    torch.testing.assert_close(single.normal[0], frames.normal[1])


@pytest.mark.parametrize("method", ["rmf", "frenet"])
def test_curves_of_several_orders_in_one_batch_are_each_curve_alone(method):
    """A sequence of control-point tensors of different orders gives, in turn, each one's points and frames as if
    it were alone (the shape fit's pre-fit batches the orders it may try), gradients included."""
    s = torch.linspace(0, 1, 12, dtype=F64)
    cubic = s_shaped_cubic().clone()
    cubic[0, 1, 2] += 0.03  # non-planar, so Frenet is defined along the whole curve
    quadratic = torch.cat([planar_quadratic(), planar_quadratic().flip(1) * 1.1])
    groups = [quadratic.clone().requires_grad_(), cubic.clone().requires_grad_()]
    points, frames = bezier_frames(groups, s, method)
    assert points.shape == (3, 12, 3)
    for value, parts in zip((points, *frames), zip(*[(p, *f) for p, f in (bezier_frames(g, s, method) for g in groups)])):
        torch.testing.assert_close(value, torch.cat(parts), atol=0, rtol=0)
    (points.sum() + frames.normal[:, :, 1].sum()).backward()
    alone = [g.detach().clone().requires_grad_() for g in groups]
    for g in alone:
        p, f = bezier_frames(g, s, method)
        (p.sum() + f.normal[:, :, 1].sum()).backward()
    for g, a in zip(groups, alone):
        torch.testing.assert_close(g.grad, a.grad, atol=1e-15, rtol=0)
    with pytest.raises(ShapeError, match="non-empty sequence"):
        bezier_frames([], s, method)


def test_gradcheck_rmf_and_frenet():
    s = torch.linspace(0, 1, 6, dtype=F64)
    cp = s_shaped_cubic().requires_grad_()

    def rmf(c):
        return torch.cat(bezier_frames(c, s, "rmf")[1], dim=-1)

    assert torch.autograd.gradcheck(rmf, (cp,))
    cp2 = planar_quadratic().clone()
    cp2[0, 1, 1] = 0.03  # non-planar
    cp2.requires_grad_()
    assert torch.autograd.gradcheck(lambda c: torch.cat(bezier_frames(c, s, "frenet")[1], dim=-1), (cp2,))


def sampled_curves():
    """Sampled curves ``(points, tangents, start normals)``, 6 of them: 0-2 smooth (two random cubics and a twisted
    one), then degenerate ones: 3 with two coincident samples (a skipped chord reflection), 4 with a zero tangent,
    5 whose tangent reverses halfway."""
    g = torch.Generator().manual_seed(5)
    s = torch.linspace(0, 1, 12, dtype=F64)
    cp = torch.cat([torch.randn(2, 4, 3, generator=g, dtype=F64), twisted_cubic(),
                    torch.randn(3, 4, 3, generator=g, dtype=F64)])
    points, tangents = bezier_points(cp, s), bezier_derivative(cp, s, 1)
    points[3, 6] = points[3, 5]
    tangents[4, 4] = 0.0
    tangents[5, 7:] = -tangents[5, 7:]
    return points, tangents, torch.randn(6, 3, generator=g, dtype=F64)


def test_rmf_numba_kernels_equal_the_torch_operations():
    """The CPU path (numba kernels, float64 inside) and the torch path (the prefix product): the same frames and
    the same gradients, the degenerate samples' skipped reflections and zero tangents included; in float32 (smooth
    curves) the same to float32 rounding."""
    points, tangents, normals = sampled_curves()
    weights = [torch.randn(points.shape, generator=torch.Generator().manual_seed(k), dtype=F64) for k in range(3)]

    def values_and_grads(f, dtype, rows):
        inputs = [v[rows].to(dtype).requires_grad_() for v in (points, tangents, normals)]
        frames = f(*inputs)
        sum((v * w[rows].to(dtype)).sum() for v, w in zip(frames, weights)).backward()
        return [v.detach() for v in frames] + [v.grad for v in inputs]

    for dtype, rows, atol in ((F64, slice(None), 1e-12), (torch.float32, slice(0, 3), 1e-4)):
        fast = values_and_grads(rotation_minimizing_frames, dtype, rows)
        for a, b in zip(fast, values_and_grads(_rmf_torch, dtype, rows)):
            assert a.dtype == dtype and torch.isfinite(a).all()
            torch.testing.assert_close(a, b, atol=atol, rtol=0)


@pytest.mark.parametrize("rmf", [rotation_minimizing_frames, _rmf_torch], ids=["numba", "torch"])
def test_gradcheck_rmf_paths(rmf):
    points, tangents, normals = sampled_curves()
    inputs = [v[:3, :7].clone().requires_grad_() if v.dim() == 3 else v[:3].clone().requires_grad_()
              for v in (points, tangents, normals)]
    assert torch.autograd.gradcheck(lambda *a: torch.cat(rmf(*a), dim=-1), inputs)


def test_rmf_coincident_points_stay_finite():
    cp = torch.tensor([[[0.0, 0.0, 0.3], [0.0, 0.0, 0.3], [0.1, 0.0, 0.4]]], dtype=F64, requires_grad=True)
    s = torch.linspace(0, 1, 10, dtype=F64)  # p'(0) = 0
    pts = bezier_points(cp, s)
    frames = rotation_minimizing_frames(pts, bezier_derivative(cp, s, 1), torch.tensor([[0.0, 1.0, 0.0]], dtype=F64))
    assert all(torch.isfinite(v).all() for v in frames)
    (grad,) = torch.autograd.grad(frames.normal.sum(), cp)
    assert torch.isfinite(grad).all()
    _, frames = bezier_frames(cp, s, "rmf")  # takes the tangent along p'' where p' = 0
    assert_orthonormal_right_handed(frames)
    torch.testing.assert_close(frames.tangent[0, 0], torch.tensor([1.0, 0.0, 1.0], dtype=F64) / 2**0.5)


def test_shape_errors():
    with pytest.raises(ShapeError, match="tangents"):
        rotation_minimizing_frames(torch.zeros(1, 4, 3), torch.zeros(1, 5, 3), torch.zeros(1, 3))


def bezier_test_curves(n, generator):
    """Control points ``(4, n+1, 3)`` float64 of order ``n``: two random curves, a straight one (its start normal
    from the fallback axis) and, for ``n >= 2``, one whose first two control points coincide (``p'(0) = 0``: the
    tangent there is ``p''``)."""
    cp = torch.randn(4, n + 1, 3, generator=generator, dtype=F64)
    cp[2] = torch.linspace(0, 1, n + 1, dtype=F64)[:, None] * torch.tensor([0.1, 0.2, 0.05], dtype=F64) + 0.3
    if n >= 2:
        cp[3, 1] = cp[3, 0]
    return cp


@pytest.mark.parametrize("n", [1, 2, 3, 5])
def test_bezier_frames_compiled_path_equals_the_torch_operations(n):
    """``bezier_frames``' CPU path (one numba call each way, float64 inside) gives the torch operations' points,
    frames and control-point gradients: to 1e-12 in float64 (straight curves and a zero ``p'(0)`` included), to
    float32 rounding in float32."""
    s = torch.linspace(0, 1, 9, dtype=F64)
    cp = bezier_test_curves(n, torch.Generator().manual_seed(n))
    weights = [torch.randn(4, 9, 3, generator=torch.Generator().manual_seed(10 + k), dtype=F64) for k in range(4)]

    def values_and_grad(f, dtype):
        c = cp.detach().to(dtype).clone().requires_grad_()
        points, frames = f(c, s.to(dtype))
        outputs = [points, *frames]
        sum((v * w.to(dtype)).sum() for v, w in zip(outputs, weights)).backward()
        return [v.detach() for v in outputs] + [c.grad]

    for dtype, atol in ((F64, 1e-12), (torch.float32, 2e-5)):
        fast = values_and_grad(lambda c, t: bezier_frames(c, t, "rmf"), dtype)
        slow = values_and_grad(lambda c, t: _bezier_frames_torch([c], t, "rmf"), dtype)
        for a, b in zip(fast, slow):
            assert a.dtype == dtype and torch.isfinite(a).all()
            torch.testing.assert_close(a, b, atol=atol * max(1.0, float(b.abs().max())), rtol=0)


def test_gradcheck_bezier_frames_compiled_path():
    s = torch.linspace(0, 1, 7, dtype=F64)
    cp = torch.randn(2, 4, 3, generator=torch.Generator().manual_seed(3), dtype=F64).requires_grad_()
    assert torch.autograd.gradcheck(lambda c: torch.cat([bezier_frames(c, s)[0], *bezier_frames(c, s)[1]], -1), (cp,))


def test_bezier_weights_are_the_closed_form_derivatives():
    """Row k of ``bezier_weights`` applied to control points is ``bezier_derivative``'s k-th derivative (row 0 the
    points); zero beyond the order."""
    s = torch.linspace(0, 1, 5, dtype=F64)
    for n in (1, 2, 4):
        cp = torch.randn(1, n + 1, 3, generator=torch.Generator().manual_seed(n), dtype=F64)
        w = torch.tensor(bezier_weights(n, tuple(s.tolist())))  # a copy: the cached array is read-only
        expected = [bezier_points(cp, s)] + [bezier_derivative(cp, s, k) for k in (1, 2)]
        for k in range(3):
            torch.testing.assert_close(torch.einsum("sk,bkd->bsd", w[k], cp), expected[k], atol=1e-13, rtol=0)
