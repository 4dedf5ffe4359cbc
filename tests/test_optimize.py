"""The generic fit loop: multi-start, per-group learning rates, best state kept, non-finite handling, and a
render-and-fit-back round trip through the soft rasterizer."""

import math

import numpy as np
import pytest
import torch

from pipeline.errors import ConfigError, ShapeError
from pipeline.optimize import ParamGroup, fit
from pipeline.render import SoftRasterSettings, render_hard, render_silhouette


def test_multi_start_converges_and_picks_best_start():
    """Three starts in a tilted double well end in different minima with clearly different losses (about -0.31 and
    +0.29): each converges to its own well's minimum (the roots of f' = 0), the best start is the argmin of the
    per-start losses (here the middle one, neither the first nor the last), and the state returned is that start's."""

    def f(x):
        return (x**2 - 1) ** 2 + 0.3 * x

    def loss(p, it):
        return f(p["x"]).sum(-1)

    init = torch.tensor([[1.5], [-2.0], [2.0]], dtype=torch.float64)
    result = fit({"x": ParamGroup(init=init, lr=0.05)}, loss, iterations=400)
    assert result.history.shape == (400, 3) and result.best_loss.shape == (3,)
    roots = sorted(r.real for r in np.roots([4.0, 0.0, -4.0, 0.3]) if abs(r.imag) < 1e-12)
    left, right = roots[0], roots[2]  # the two minima; roots[1] is the barrier's top
    expected = torch.tensor([right, left, right], dtype=torch.float64)
    torch.testing.assert_close(result.best_params["x"][:, 0], expected, atol=1e-4, rtol=0)
    torch.testing.assert_close(result.best_loss, f(expected), atol=1e-8, rtol=0)
    assert float(result.best_loss[0] - result.best_loss[1]) > 0.5  # clearly different ends
    assert result.best_start == int(torch.argmin(result.best_loss)) == 1
    torch.testing.assert_close(result.params_of()["x"], result.best_params["x"][1], atol=0, rtol=0)
    torch.testing.assert_close(result.params_of()["x"], torch.tensor([left], dtype=torch.float64), atol=1e-4, rtol=0)


def test_best_state_is_kept_not_last():
    # Loss that gets worse after iteration 5: the best state must be the one seen at iteration <= 5.
    def loss(p, it):
        return (p["x"] ** 2).sum(-1) + (it > 5) * 100.0

    result = fit({"x": ParamGroup(init=torch.ones(1, 1), lr=0.01)}, loss, iterations=20)
    assert int(result.best_iteration[0]) == 5
    assert float(result.best_loss[0]) == pytest.approx(float(result.history[5, 0]))


def test_group_learning_rates_are_separate():
    def loss(p, it):
        return ((p["a"] - 1) ** 2).sum(-1) + ((p["b"] - 1) ** 2).sum(-1)

    result = fit({"a": ParamGroup(init=torch.zeros(1, 1), lr=0.05), "b": ParamGroup(init=torch.zeros(1, 1), lr=0.0)},
                 loss, iterations=100)
    assert float(result.params_of()["a"]) > 0.9
    assert float(result.params_of()["b"]) == 0.0


def test_a_group_at_rate_zero_is_held_exactly_and_gets_no_gradient():
    """A group at rate 0 is a constant of the fit (no gradient, no Adam state): it comes back bit for bit as its
    init, and the moving group ends as a fit of it alone does, to float rounding; with nothing moving the loop
    only evaluates (the history holds the init's loss at every iteration)."""
    seen = []

    def loss(p, it):
        seen.append(p["b"].requires_grad)
        return ((p["a"] - p["b"]) ** 2).sum(-1)

    b = torch.tensor([[0.3, -0.7]], dtype=torch.float64)
    held = fit({"a": ParamGroup(init=torch.zeros(1, 2, dtype=torch.float64), lr=0.05),
                "b": ParamGroup(init=b, lr=0.0)}, loss, iterations=50)
    assert not any(seen) and torch.equal(held.best_params["b"], b)
    alone = fit({"a": ParamGroup(init=torch.zeros(1, 2, dtype=torch.float64), lr=0.05)},
                lambda p, it: ((p["a"] - b) ** 2).sum(-1), iterations=50)
    torch.testing.assert_close(held.best_params["a"], alone.best_params["a"], atol=1e-12, rtol=0)
    torch.testing.assert_close(held.history, alone.history, atol=1e-12, rtol=0)
    frozen = fit({"b": ParamGroup(init=b, lr=0.0)}, lambda p, it: (p["b"] ** 2).sum(-1), iterations=5)
    assert torch.equal(frozen.best_params["b"], b)
    torch.testing.assert_close(frozen.history, torch.full((5, 1), 0.58, dtype=torch.float64), atol=1e-15, rtol=0)


def test_fused_adam_steps_as_the_default_loop_to_float_rounding():
    """``fused_adam``: Adam's fused kernel takes the default loop's steps to float32 rounding (not bit for bit, which
    is why the pose fit keeps the default)."""
    target = torch.linspace(-1.0, 1.0, 12).reshape(3, 4)

    def loss(p, it):
        return ((p["x"] - target) ** 2 * torch.arange(1.0, 5.0)).sum(-1)

    runs = [fit({"x": ParamGroup(init=torch.zeros(3, 4), lr=0.02)}, loss, iterations=40, fused_adam=fused)
            for fused in (False, True)]
    torch.testing.assert_close(runs[1].best_params["x"], runs[0].best_params["x"], atol=1e-5, rtol=0)
    assert float((runs[0].best_params["x"]).abs().max()) > 0.5  # it moved


def test_gradients_given_by_the_loss_function_take_autograds_place():
    """A loss function may return its losses with a function of its own gradients (``LossFn``): the fit then steps
    exactly as with autograd's gradients, and a start whose loss is not finite gets weight 0 (as autograd's
    indexed sum gives it no gradient)."""
    target = torch.tensor([[1.0, -2.0], [0.5, 0.5], [3.0, 0.0]], dtype=torch.float64)
    weights_seen = []

    def autograd_loss(p, it):
        loss = ((p["x"] - target) ** 2).sum(-1)
        return torch.where(torch.arange(3) == 2, loss + (math.inf if it == 3 else 0.0), loss)

    def given(p, it):
        loss = autograd_loss(p, it).detach()

        def gradients(weights):
            weights_seen.append(weights.clone())
            return {"x": 2.0 * (p["x"].detach() - target) * weights[:, None]}

        return loss, gradients

    init = torch.zeros(3, 2, dtype=torch.float64)
    a = fit({"x": ParamGroup(init=init, lr=0.1)}, autograd_loss, iterations=20)
    b = fit({"x": ParamGroup(init=init, lr=0.1)}, given, iterations=20)
    torch.testing.assert_close(b.best_params["x"], a.best_params["x"], atol=1e-14, rtol=0)
    torch.testing.assert_close(b.history, a.history, atol=1e-14, rtol=0)
    assert weights_seen[3].tolist() == [1.0, 1.0, 0.0] and weights_seen[4].tolist() == [1.0, 1.0, 1.0]


def test_non_finite_losses_never_win_and_do_not_poison():
    def loss(p, it):
        value = (p["x"] ** 2).sum(-1)
        return torch.where(torch.arange(2) == 1, torch.full_like(value, math.nan), value)

    result = fit({"x": ParamGroup(init=torch.ones(2, 1), lr=0.1)}, loss, iterations=30)
    assert result.best_start == 0 and math.isinf(float(result.best_loss[1]))
    assert torch.isfinite(result.best_params["x"]).all()


def test_bad_configuration():
    with pytest.raises(ConfigError, match="iterations"):
        fit({"x": ParamGroup(init=torch.ones(1, 1), lr=0.1)}, lambda p, i: p["x"].sum(-1), iterations=0)
    with pytest.raises(ShapeError, match="start dimension"):
        fit({"x": ParamGroup(init=torch.ones(1, 1), lr=0.1), "y": ParamGroup(init=torch.ones(2, 1), lr=0.1)},
            lambda p, i: p["x"].sum(-1), iterations=1)
    with pytest.raises(ShapeError, match="loss per start"):
        fit({"x": ParamGroup(init=torch.ones(2, 1), lr=0.1)}, lambda p, i: p["x"].sum(), iterations=1)


def test_round_trip_translation_through_the_rasterizer():
    """Render a square at a known translation, fit the translation back from the binary mask."""
    H, W = 48, 64
    K = torch.tensor([[80.0, 0, 31.5], [0, 80.0, 23.5], [0, 0, 1]], dtype=torch.float64)
    square = torch.tensor([[-0.05, -0.05, 0], [0.05, -0.05, 0], [0.05, 0.05, 0], [-0.05, 0.05, 0]],
                          dtype=torch.float64)
    faces = torch.tensor([[0, 1, 2], [0, 2, 3]])
    truth = torch.tensor([0.03, -0.02, 0.5], dtype=torch.float64)
    mask = render_hard((square + truth)[None], faces, K, (H, W))[0].double()
    settings = SoftRasterSettings.from_sigma(0.25)

    def loss(p, it):
        S = render_silhouette(square[None] + p["t"][:, None, :], faces, K, (H, W), settings)
        return ((S - mask) ** 2).sum(dim=(-2, -1))

    init = torch.tensor([[0.0, 0.0, 0.5], [0.01, 0.01, 0.5]], dtype=torch.float64)
    result = fit({"t": ParamGroup(init=init, lr=2e-3)}, loss, iterations=300)
    fitted = result.params_of()["t"]
    torch.testing.assert_close(fitted[:2], truth[:2], atol=2e-3, rtol=0)  # 0.3 px at this scale
    assert abs(float(fitted[2] - truth[2])) < 5e-3


def test_final_lr_factor_decays_the_step_size_geometrically():
    # A constant gradient makes Adam step by exactly lr (bias-corrected), so x after N steps is the sum of the rates.
    def loss(p, it):
        return p["x"].sum(-1)

    N, lr, factor = 11, 0.1, 0.01
    result = fit({"x": ParamGroup(init=torch.zeros(1, 1, dtype=torch.float64), lr=lr)}, loss, iterations=N,
                 final_lr_factor=factor)
    rates = [lr * factor ** (i / (N - 1)) for i in range(N)]
    # history[i] is the loss before step i, i.e. minus the sum of the first i rates.
    torch.testing.assert_close(result.history[:, 0], -torch.tensor([sum(rates[:i]) for i in range(N)],
                                                                     dtype=torch.float64), atol=1e-6, rtol=0)
    with pytest.raises(ConfigError, match="final_lr_factor"):
        fit({"x": ParamGroup(init=torch.zeros(1, 1), lr=lr)}, loss, iterations=2, final_lr_factor=0.0)


def test_final_lr_factor_schedule_follows_the_iteration_count_across_skipped_steps():
    # Every start's loss is NaN at iteration 3: no step is taken there, and the later steps keep their own rates.
    def loss(p, it):
        value = p["x"].sum(-1)
        return torch.full_like(value, math.nan) if it == 3 else value

    N, lr, factor = 9, 0.1, 0.05
    result = fit({"x": ParamGroup(init=torch.zeros(1, 1, dtype=torch.float64), lr=lr)}, loss, iterations=N,
                 final_lr_factor=factor)
    rates = [0.0 if i == 3 else lr * factor ** (i / (N - 1)) for i in range(N)]
    finite = torch.isfinite(result.history[:, 0])
    assert finite.tolist() == [i != 3 for i in range(N)]
    expected = -torch.tensor([sum(rates[:i]) for i in range(N)], dtype=torch.float64)
    torch.testing.assert_close(result.history[finite, 0], expected[finite], atol=1e-6, rtol=0)


def test_start_rates_match_each_start_run_alone_at_its_own_rate():
    """Three starts of a non-quadratic loss, one batch with per-start rate factors (1, 0.2, 3), against each start
    fitted alone at ``lr * factor`` (same decay): the histories and the kept states agree (Adam's moments are
    each start's own gradients'); a plain batch at one rate does not (the factors matter)."""

    def loss(p, it):
        x = p["x"]
        return ((x**2 - 1) ** 2).sum(-1) + 0.3 * x[:, 0] * x[:, 1]

    init = torch.tensor([[1.5, -0.7], [-2.0, 0.4], [0.3, 0.9]], dtype=torch.float64)
    factors = torch.tensor([1.0, 0.2, 3.0], dtype=torch.float64)
    lr, N = 0.02, 40
    batch = fit({"x": ParamGroup(init=init, lr=lr, start_rates=factors)}, loss, iterations=N, final_lr_factor=0.1)
    for s in range(3):
        alone = fit({"x": ParamGroup(init=init[s:s + 1], lr=lr * float(factors[s]))}, loss, iterations=N,
                    final_lr_factor=0.1)
        torch.testing.assert_close(batch.history[:, s], alone.history[:, 0], atol=1e-9, rtol=0)
        torch.testing.assert_close(batch.best_params["x"][s], alone.best_params["x"][0], atol=1e-9, rtol=0)
    plain = fit({"x": ParamGroup(init=init, lr=lr)}, loss, iterations=N, final_lr_factor=0.1)
    assert float((plain.history[:, 1:] - batch.history[:, 1:]).abs().max()) > 1e-3
    for bad in (torch.ones(2), torch.tensor([1.0, 0.0, 1.0]), torch.tensor([1.0, math.nan, 1.0])):
        with pytest.raises(ConfigError, match="start_rates"):
            ParamGroup(init=init, lr=lr, start_rates=bad)


@pytest.mark.parametrize("fused", [False, True])
def test_a_fit_begun_with_the_moments_of_another_takes_adams_step_from_them(fused):
    """Adam's state carried between fits (``FitResult.moments_of`` -> ``fit(moments=...)``, a tracked video's next
    frame): the second fit's first step is Adam's update written out by hand from the given averages and step
    count (not Adam's first step, which moves every coordinate by about the rate), every start begins with the one
    start's moments, and the count goes on. Without them, or with moments of another shape (another curve order),
    the fit begins as Adam does."""
    scale = torch.tensor([1.0, 0.1, 10.0], dtype=torch.float64)

    def loss(p, it):
        return (scale * (p["x"] - 3.0) ** 2).sum(-1)

    lr, (b1, b2), eps = 0.05, (0.9, 0.999), 1e-8
    first = fit({"x": ParamGroup(init=torch.zeros(2, 3, dtype=torch.float64), lr=lr)}, loss, iterations=12,
                fused_adam=fused)
    m0 = first.moments_of(1)["x"]
    assert m0.step == 12 and m0.exp_avg.shape == (1, 3) and first.moments["x"].exp_avg.shape == (2, 3)
    x0 = torch.tensor([[1.0, 2.0, 2.5], [0.5, 1.0, 2.9]], dtype=torch.float64)  # the next frame's starts
    carried = fit({"x": ParamGroup(init=x0, lr=lr)}, loss, iterations=2, fused_adam=fused, moments={"x": m0})
    g = 2.0 * scale * (x0 - 3.0)
    m, v, t = b1 * m0.exp_avg + (1 - b1) * g, b2 * m0.exp_avg_sq + (1 - b2) * g**2, m0.step + 1
    expected = x0 - lr * (m / (1 - b1**t)) / ((v / (1 - b2**t)).sqrt() + eps)
    torch.testing.assert_close(carried.history[1], loss({"x": expected}, 0), rtol=1e-10, atol=1e-12)
    assert carried.moments["x"].step == 14
    adam_first = x0 - lr * torch.sign(g)  # Adam afresh: about the rate in every coordinate
    afresh = fit({"x": ParamGroup(init=x0, lr=lr)}, loss, iterations=2, fused_adam=fused)
    torch.testing.assert_close(afresh.history[1], loss({"x": adam_first}, 0), rtol=1e-6, atol=1e-9)
    assert float((carried.history[1] - afresh.history[1]).abs().max()) > 1e-3
    other = fit({"x": ParamGroup(init=torch.zeros(2, 4, dtype=torch.float64), lr=lr)},
                lambda p, it: ((p["x"] - 3.0) ** 2).sum(-1), iterations=3, fused_adam=fused)
    mismatched = fit({"x": ParamGroup(init=x0, lr=lr)}, loss, iterations=2, fused_adam=fused,
                     moments=other.moments_of(0))
    torch.testing.assert_close(mismatched.history, afresh.history, rtol=0, atol=0)
