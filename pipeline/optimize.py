"""The one fit loop both estimators use: Adam over named parameter groups, many starts in one batch, best kept.

Every parameter tensor is batch-first over *starts* (independent hypotheses optimised together, one render
batch); the loss function returns one loss per start. Per start, the parameters of the lowest loss seen are kept
(not the last ones), and the result names the best start.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass

import torch
from tqdm.auto import tqdm

from pipeline.errors import ConfigError, ShapeError

log = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True)
class ParamGroup:
    """A named parameter with its own learning rate.

    Fields:
        init: (S, ...) initial value, batch-first over starts.
        lr: Adam learning rate (0 freezes the group).
        start_rates: optional (S,) factors > 0 of ``lr``, one per start: start ``s``'s Adam step is scaled by
            ``start_rates[s]`` (its moments are its own gradients', as in a run of that start alone at
            ``lr * start_rates[s]``). None: every start at ``lr``.
    """

    init: torch.Tensor
    lr: float
    start_rates: torch.Tensor | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.init, torch.Tensor) or self.init.dim() < 1:
            raise ShapeError("ParamGroup.init: expected a tensor of shape (S, ...) batch-first over starts")
        if not (self.lr >= 0 and math.isfinite(self.lr)):
            raise ConfigError(f"ParamGroup.lr: expected a finite number >= 0, got {self.lr!r}")
        rates = self.start_rates
        if rates is not None and (not isinstance(rates, torch.Tensor) or rates.shape != self.init.shape[:1]
                                  or not bool(torch.isfinite(rates).all()) or not bool((rates > 0).all())):
            raise ConfigError(f"ParamGroup.start_rates: expected None or a tensor of {self.init.shape[0]} finite "
                              f"factors > 0 (one per start), got {rates!r}")


@dataclass(frozen=True, kw_only=True)
class FitResult:
    """Outcome of :func:`fit`.

    Fields:
        best_params: name -> (S, ...) per-start parameters of the lowest loss seen.
        best_loss: (S,) lowest loss of each start.
        best_iteration: (S,) iteration at which it was seen.
        history: (N, S) loss of every start at every iteration (before that iteration's step).
        best_start: index of the start with the lowest loss.
        seconds: wall time of the loop.
        moments: name -> Adam's state of every start of each moving group after the last step
            (:class:`AdamMoments`, ``(S, ...)``), to go on from in another fit (``fit(moments=...)``); empty when
            nothing moved or no step was taken.
    """

    best_params: Mapping[str, torch.Tensor]
    best_loss: torch.Tensor
    best_iteration: torch.Tensor
    history: torch.Tensor
    best_start: int
    seconds: float
    moments: Mapping[str, "AdamMoments"] = dataclasses.field(default_factory=dict)

    def params_of(self, start: int | None = None) -> dict[str, torch.Tensor]:
        """Parameters of one start (default: the best), without the start dimension."""
        s = self.best_start if start is None else start
        return {name: value[s] for name, value in self.best_params.items()}

    def moments_of(self, start: int | None = None) -> dict[str, "AdamMoments"]:
        """Adam's state of one start (default: the best), ``(1, ...)`` per group, for ``fit(moments=...)``."""
        s = self.best_start if start is None else start
        return {name: m.of(s) for name, m in self.moments.items()}


@dataclass(frozen=True, kw_only=True, eq=False)
class AdamMoments:
    """Adam's state of a parameter group: a fit's steps so far, and the running averages of its gradients and of
    their squares, to start another fit with (a video's next frame: the step sizes and the motion the last frame's
    fit ended with, instead of Adam's first steps of about the learning rate in every coordinate).

    Compared by identity (its tensors have no single truth value).

    Fields:
        step: the number of steps the averages are over (Adam's bias correction).
        exp_avg: ``(S, ...)`` first moment, batch-first over starts (``S`` may be 1: then every start of the fit
            it is given to begins with it).
        exp_avg_sq: ``(S, ...)`` second moment.
    """

    step: float
    exp_avg: torch.Tensor
    exp_avg_sq: torch.Tensor

    def of(self, start: int) -> "AdamMoments":
        """One start's moments, ``(1, ...)``."""
        return AdamMoments(step=self.step, exp_avg=self.exp_avg[start:start + 1],
                           exp_avg_sq=self.exp_avg_sq[start:start + 1])


def _fused_adam(params) -> bool | None:
    """Adam's fused kernel (one call per group instead of a loop of small operations) where torch has it: floating
    point parameters on CPU or CUDA; else torch's default."""
    return True if all(p.is_floating_point() and p.device.type in ("cpu", "cuda") for p in params) else None


#: ``(params, iteration) -> (S,) losses`` (differentiated by autograd), or ``-> (losses, gradients)`` where the
#: caller computes the gradients itself: ``gradients(weights (S,) float64) -> {name: dL/d params[name]}`` of ``L =
#: sum_s weights_s loss_s`` (the loop passes 1 for a finite loss, 0 for another).
LossFn = Callable[[Mapping[str, torch.Tensor], int],
                  torch.Tensor | tuple[torch.Tensor, Callable[[torch.Tensor], Mapping[str, torch.Tensor]]]]


def fit(
    groups: Mapping[str, ParamGroup],
    loss_fn: LossFn,
    *,
    iterations: int,
    progress: bool = False,
    description: str = "fit",
    betas: tuple[float, float] = (0.9, 0.999),
    final_lr_factor: float = 1.0,
    fused_adam: bool = False,
    moments: Mapping[str, AdamMoments] | None = None,
) -> FitResult:
    """Minimise ``loss_fn`` with Adam, keeping each start's best parameters.

    Args:
        groups: name -> ParamGroup; all ``init`` tensors share the leading start dimension S.
        loss_fn: ``(params, iteration) -> (S,)`` losses, one per start (the starts must be independent), or
            ``(losses, gradients)`` with the gradients computed by the caller (``LossFn``; no autograd graph: a
            step's overhead is smaller).
        iterations: number of loss evaluations / Adam steps N >= 1.
        progress: show a tqdm progress bar.
        final_lr_factor: learning-rate schedule: every group's rate decays geometrically from ``lr`` at the first
            step to ``lr * final_lr_factor`` at the last (``lr * final_lr_factor ** (i / (N - 1))`` at step ``i``);
            1 keeps it constant.
        fused_adam: Adam's fused kernel where torch has one (floating point parameters on CPU or CUDA): one call per
            group instead of a loop of small operations, with other float rounding than the default loop (the
            shape fit uses it; the pose fit's figures were measured with the default).
        moments: name -> Adam's state to begin that group with (e.g. ``FitResult.moments_of()`` of the fit before),
            its ``(1, ...)`` or ``(S, ...)`` averages matching the group's ``(S, ...)`` shape; a group not named, or
            whose shape does not match (another curve order), begins as Adam does, with zeros. None: every group.

    Returns:
        FitResult. Non-finite losses count as +inf (never best); non-finite gradients are zeroed with a warning.
    """
    if not isinstance(iterations, int) or iterations < 1:
        raise ConfigError(f"iterations: expected an int >= 1, got {iterations!r}")
    if not groups:
        raise ConfigError("groups: expected at least one parameter group")
    if not (0 < final_lr_factor and math.isfinite(final_lr_factor)):
        raise ConfigError(f"final_lr_factor: expected a finite number > 0, got {final_lr_factor!r}")
    starts = {g.init.shape[0] for g in groups.values()}
    if len(starts) != 1:
        raise ShapeError(f"groups: every init must share the start dimension S, got sizes {sorted(starts)}")
    (S,) = starts
    # A group at rate 0 stays at its init (Adam's step is 0 times a finite number): it is held as a constant, with
    # no gradient, no Adam state and no best-state bookkeeping (e.g. the shape fit's radius offsets by default).
    moving = [name for name, g in groups.items() if g.lr > 0]
    params = {name: g.init.detach().clone().requires_grad_(name in moving) for name, g in groups.items()}
    scaled = {name: g.start_rates.to(params[name]).view(-1, *([1] * (params[name].dim() - 1)))
              for name, g in groups.items() if g.start_rates is not None and name in moving}  # (S, 1, ...) factors
    optimizer = torch.optim.Adam(  # (a placeholder group when nothing moves: the loop then only evaluates)
        [{"params": [params[name]], "lr": groups[name].lr} for name in moving] or [{"params": [torch.zeros(1)]}],
        betas=betas, fused=_fused_adam(params[name] for name in moving) if fused_adam else None,
    )
    if moments:
        _load_moments(optimizer, [params[name] for name in moving], [moments.get(name) for name in moving])
    schedule = torch.optim.lr_scheduler.LambdaLR(  # rate of step it: lr * final_lr_factor ** (it / (N - 1))
        optimizer, lambda it: final_lr_factor ** (it / max(iterations - 1, 1)))
    best = {name: p.detach().clone() for name, p in params.items()}
    some = next(iter(params.values()))
    best_loss = torch.full((S,), math.inf, dtype=torch.float64, device=some.device)
    best_iteration = torch.zeros(S, dtype=torch.long, device=some.device)
    history = []  # (S,) float64 losses, one per iteration
    warned = False
    t0 = time.perf_counter()
    for it in tqdm(range(iterations), desc=description, disable=not progress, leave=False):
        for name in moving:  # (optimizer.zero_grad(set_to_none=True), without its profiler hooks)
            params[name].grad = None
        loss = loss_fn(params, it)
        loss, gradients = (loss, None) if isinstance(loss, torch.Tensor) else loss
        if loss.shape != (S,):
            raise ShapeError(f"loss_fn: expected a loss per start of shape ({S},), got {tuple(loss.shape)}")
        value = loss.detach().to(torch.float64)
        finite = torch.isfinite(value)
        value = torch.where(finite, value, math.inf)
        history.append(value)
        improved = value < best_loss
        if bool(improved.any()):
            best_loss = torch.minimum(value, best_loss)
            best_iteration.masked_fill_(improved, it)
            for name in moving:
                p = params[name]
                best[name] = torch.where(improved.view(-1, *([1] * (p.dim() - 1))), p.detach(), best[name])
        if not moving:
            continue
        if not bool(finite.any()):
            schedule.step()  # a skipped step keeps the schedule on the iteration count
            continue
        if gradients is not None:
            computed = gradients(finite.to(torch.float64))
            for name in moving:
                params[name].grad = computed[name].to(params[name])
        elif bool(finite.all()):  # (an indexed sum would add an indexing node to every step's backward pass)
            loss.sum().backward()
        else:
            loss[finite].sum().backward()
        grads = [params[name].grad for name in moving if params[name].grad is not None]
        # one check of every gradient: their sums are finite when all entries are (a finite sum that overflowed
        # is checked entry by entry too)
        if grads and not bool(torch.isfinite(torch.stack([g.sum() for g in grads])).all()):
            for p in params.values():
                if p.grad is not None and not bool(torch.isfinite(p.grad).all()):
                    if not warned:
                        log.warning("%s: non-finite gradient at iteration %d zeroed", description, it)
                        warned = True
                    p.grad = torch.nan_to_num(p.grad, nan=0.0, posinf=0.0, neginf=0.0)
        before = {name: params[name].detach().clone() for name in scaled}
        optimizer.step()
        with torch.no_grad():  # a start's own rate: its step scaled (Adam's moments are its gradients' alone)
            for name, factor in scaled.items():
                params[name].copy_(before[name] + factor * (params[name] - before[name]))
        schedule.step()
    seconds = time.perf_counter() - t0
    best_start = int(torch.argmin(best_loss))
    return FitResult(best_params=best, best_loss=best_loss, best_iteration=best_iteration,
                     history=torch.stack(history).cpu(),
                     best_start=best_start, seconds=seconds, moments=_saved_moments(optimizer, params, moving))


def _load_moments(optimizer: torch.optim.Adam, params: list[torch.Tensor],
                  moments: list[AdamMoments | None]) -> None:
    """Begin ``optimizer``'s Adam state of each of ``params`` ``(S, ...)`` with its ``moments`` (broadcast over the
    starts) where given and of a matching shape; through ``load_state_dict``, which puts the step count where this
    Adam (fused or not) keeps it."""
    state = {}
    for index, (p, m) in enumerate(zip(params, moments)):
        if m is None or m.exp_avg.shape[1:] != p.shape[1:] or m.exp_avg.shape[0] not in (1, p.shape[0]):
            continue
        state[index] = {"step": torch.tensor(float(m.step)),
                        "exp_avg": m.exp_avg.to(p).expand_as(p).clone(),
                        "exp_avg_sq": m.exp_avg_sq.to(p).expand_as(p).clone()}
    if state:
        optimizer.load_state_dict({"state": state, "param_groups": optimizer.state_dict()["param_groups"]})


def _saved_moments(optimizer: torch.optim.Adam, params: Mapping[str, torch.Tensor],
                   moving: list[str]) -> dict[str, AdamMoments]:
    """Adam's state of each moving group after the last step (none before a first step)."""
    saved = {}
    for name in moving:
        state = optimizer.state.get(params[name])
        if state and "exp_avg" in state:
            saved[name] = AdamMoments(step=float(state["step"]), exp_avg=state["exp_avg"].detach(),
                                      exp_avg_sq=state["exp_avg_sq"].detach())  # the optimizer is done with them
    return saved
