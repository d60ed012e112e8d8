"""3DGS-MCMC (Kheradmand et al. 2024) on CPU.

Every ``refine_every`` steps inside the refinement window: dead Gaussians (opacity <=
``min_opacity``) are relocated onto live ones drawn in proportion to opacity, with the paper's
opacity/scale update (:mod:`.relocation`); then the set grows by ``growth_rate`` (5%) of its size,
by sampling new copies the same way, up to ``cap_max``. With ``cap_max = 'validated'`` views
held out of training decide (:mod:`.count_rule`): the set grows to ``count_ceiling`` times its
starting count, and at the last refinement the trainer tries it cut to smaller counts, each
fine-tuned alike, and keeps the smallest that scores as well as the best on the held-out views.
With ``cap_max = 'auto'`` the training loss decides instead (:func:`keeps_growing`): the set grows while the mean training loss over the
last ``auto_span`` refinement intervals still falls by at least ``auto_min_drop`` of the mean over
the ``auto_span`` intervals before them, and stops for good, at its count then, after
``auto_patience`` refinements in a row where it does not. After every step the positions get the
opacity-gated, covariance-shaped noise (isotropic, or along the camera ray in 'ray' mode). The
paper's L1 regularisers on opacity and scale come back from :meth:`MCMCStrategy.regularization_loss`
for the trainer to add to its loss.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any, ClassVar, Literal

import torch
from torch import Tensor

from ..schedule import Schedule
from . import row_ops
from .base import StepContext, Strategy, StrategyError
from .count_rule import COUNT_CAP, COUNT_START, VALIDATED
from .row_ops import Optimizers, Params, num_gaussians
from .position_noise import PositionNoise
from .relocation import N_MAX, binomial_table

MCMC_STOP_FRACTION = 25_000 / 30_000
"""3DGS-MCMC refines until step 25k of 30k; a run of any length stops at the same fraction."""

AUTO = "auto"
"""``cap_max = 'auto'``: the count is decided by the training loss (:func:`keeps_growing`)."""
AUTO_LOSS, AUTO_STEPS, AUTO_MEANS, AUTO_BELOW, AUTO_CAP = (
    "auto_loss", "auto_steps", "auto_means", "auto_below", "auto_cap")
"""State of the automatic cap: the loss summed over the current window (a 0-d tensor on the
loss's device, or None), its steps, the means of the last 2 x span closed windows (floats), the
refinements in a row below the drop, and the cap once growth has stopped (None while it grows)."""
NO_CAP = 1 << 62

def keeps_growing(means: list[float], below: int, min_drop: float, span: int, patience: int
                  ) -> tuple[bool, int]:
    """One refinement of the automatic cap: (grow now?, refinements in a row below the drop).

    ``means`` are the mean training losses of the refinement windows closed so far, the newest
    last. Until there are 2 x ``span`` of them the set grows. Then, with P the mean of the
    ``span`` windows before the newest ``span`` and R the mean of the newest ``span``, the relative
    drop is d = (P - R) / P: the fall of the slow average of the loss over ``span`` refinements,
    the time the count takes to grow by (1 + growth_rate)^span. Averaging ``span`` windows damps
    the noise of a window (the views it drew, the relocations in it) by about sqrt(span), which a
    threshold of a percent or two needs. A d below ``min_drop`` (a flat or rising loss, or one
    that is not finite) adds one to ``below``, any other resets it to 0, and growth stops when
    ``below`` reaches ``patience``.
    """
    if len(means) < 2 * span:
        return True, 0
    previous = sum(means[-2 * span:-span]) / span
    recent = sum(means[-span:]) / span
    usable = math.isfinite(previous) and math.isfinite(recent) and previous > 0.0
    drop = (previous - recent) / previous if usable else 0.0
    below = below + 1 if drop < min_drop else 0
    return below < patience, below


def auto_state() -> dict[str, Any]:
    """The automatic cap's state at the start of a run (kept in the strategy state: checkpointed)."""
    return {AUTO_LOSS: None, AUTO_STEPS: 0, AUTO_MEANS: [], AUTO_BELOW: 0, AUTO_CAP: None}


def auto_add_loss(state: dict[str, Any], loss: Tensor | float) -> None:
    """Add one step's training loss to the current window (a tensor stays where it lies: no wait
    for the device until the window closes)."""
    value = loss.detach().reshape(()).to(torch.float64) if isinstance(loss, Tensor) else float(loss)
    state[AUTO_LOSS] = value if state[AUTO_LOSS] is None else state[AUTO_LOSS] + value
    state[AUTO_STEPS] += 1


def auto_close_window(state: dict[str, Any], n: int, min_drop: float, span: int, patience: int) -> int:
    """At a refinement: close the window, apply :func:`keeps_growing`, and return the cap of this
    refinement's growth (``n`` from the refinement that stops growth on, no cap before)."""
    if AUTO_MEANS not in state:  # a checkpoint from before auto_span kept the previous window's mean
        previous = state.pop("auto_previous", None)
        state[AUTO_MEANS] = [] if previous is None else [previous]
    if state[AUTO_CAP] is None and state[AUTO_STEPS] > 0:
        mean = float(state[AUTO_LOSS]) / state[AUTO_STEPS]  # the one read of the loss per refinement
        state[AUTO_LOSS], state[AUTO_STEPS] = None, 0
        means = (state[AUTO_MEANS] + [mean])[-2 * span:]
        state[AUTO_MEANS] = means
        grow, state[AUTO_BELOW] = keeps_growing(means, state[AUTO_BELOW], min_drop, span, patience)
        if not grow:
            state[AUTO_CAP] = n
    return NO_CAP if state[AUTO_CAP] is None else state[AUTO_CAP]


@dataclass
class MCMCStrategy(Strategy):
    """3DGS-MCMC: relocation of dead Gaussians, 5% growth to cap_max, noise after every step."""

    cap_max: int | Literal["auto", "validated"] | None = 30_000
    """Largest number of Gaussians (required for MCMC; the paper uses 1-3M on GPU), or
    'validated': a few training views are held out, the set grows to count_ceiling times its
    starting count, and at the last refinement the trainer tries it cut to count_cuts of its
    count (the most significant Gaussians), each candidate fine-tuned count_trial_steps steps
    from the same snapshot; the smallest whose held-out PSNR is within count_tolerance dB of the
    best candidate's (per view, with its standard error) is kept and the views return to
    training (eg-train's pipeline runs the trial); or 'auto': grow while the slow average of the
    training loss (over auto_span refinements) still falls by auto_min_drop, stop for good after
    auto_patience refinements in a row where it does not."""
    min_opacity: float = 0.005
    """Gaussians at or below this opacity are dead and get relocated."""
    growth_rate: float = 0.05
    """The set grows by this fraction at every refinement until cap_max."""
    opacity_reg: float = 0.01
    """Weight of the L1 opacity regulariser (mean activated opacity)."""
    scale_reg: float = 0.01
    """Weight of the L1 scale regulariser (mean activated scale)."""
    noise: PositionNoise = field(default_factory=PositionNoise)
    """The position noise after every step: isotropic (3DGS-MCMC), or along the camera ray
    (``--strategy.noise.mode ray``)."""
    auto_min_drop: float = 0.05
    """cap_max 'auto': the relative fall of the slow average of the training loss (the mean over
    auto_span refinement windows against the auto_span windows before) below which a refinement
    counts as not worth growing."""
    auto_span: int = 1
    """cap_max 'auto': refinement windows per slow average (:func:`keeps_growing`)."""
    auto_patience: int = 2
    """cap_max 'auto': growth stops for good after this many refinements in a row below auto_min_drop."""
    count_ceiling: float = 3.0
    """cap_max 'validated': while the count is undecided the set grows to this many times its
    count at the first refinement (the SfM points, or the random start). fox's best fixed cap was
    3.2 times its start, mouse's 1.7, beer's 1.1 (docs/results.md)."""

    CAP_WORDS: ClassVar[tuple[str, ...]] = (AUTO, VALIDATED)
    MORE_GAUSSIANS: ClassVar[str] = "a higher --strategy.count-ceiling"

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.cap_max is None:
            raise StrategyError("MCMCStrategy needs cap_max: its 5% growth per refinement is bounded only by it")
        if not (math.isfinite(self.count_ceiling) and self.count_ceiling >= 1.0):
            raise StrategyError(f"count_ceiling must be >= 1, got {self.count_ceiling}")
        if (not (math.isfinite(self.auto_min_drop) and self.auto_min_drop >= 0.0) or self.auto_patience < 1
                or self.auto_span < 1):
            raise StrategyError(f"auto_min_drop must be >= 0, auto_span and auto_patience >= 1, got "
                                f"{self.auto_min_drop}, {self.auto_span}, {self.auto_patience}")
        if not 0.0 <= self.growth_rate:
            raise StrategyError(f"growth_rate must be >= 0, got {self.growth_rate}")
        if not 0.0 < self.min_opacity < 1.0:
            raise StrategyError(f"min_opacity must be in (0, 1), got {self.min_opacity}")
        if self.opacity_reg < 0 or self.scale_reg < 0:
            raise StrategyError("opacity_reg and scale_reg must be >= 0")

    def schedule_defaults(self, schedule: Schedule) -> dict[str, int]:
        defaults = super().schedule_defaults(schedule)
        defaults["refine_stop_iter"] = int(math.floor(MCMC_STOP_FRACTION * schedule.max_steps))
        return defaults

    def initialize_state(self, scene_scale: float = 1.0, scene_center: Tensor | None = None) -> dict[str, Any]:
        state = super().initialize_state(scene_scale, scene_center)
        state["binoms"] = binomial_table(N_MAX)
        if self.cap_max == AUTO:
            state.update(auto_state())
        return state

    def regularization_loss(self, params: Params) -> Tensor:
        """opacity_reg * mean(sigmoid(o)) + scale_reg * mean(exp(s)); a scalar in the graph."""
        if num_gaussians(params) == 0:
            return params["means"].new_zeros(())
        loss = params["means"].new_zeros(())
        if self.opacity_reg > 0:
            loss = loss + self.opacity_reg * torch.sigmoid(params["opacities"]).abs().mean()
        if self.scale_reg > 0:
            loss = loss + self.scale_reg * torch.exp(params["scales"]).abs().mean()
        return loss

    def post_backward(self, ctx: StepContext) -> dict[str, int]:
        params, optimizers, state, step = ctx.params, ctx.optimizers, ctx.state, ctx.step
        counts = {"relocated": 0, "added": 0}
        if self.cap_max == AUTO and step < self.refine_stop_iter and state[AUTO_CAP] is None:
            self.track_loss(state, ctx.loss)
        if self.refine_start_iter < step < self.refine_stop_iter and step % self.refine_every == 0:
            counts.update(self.refine(params, optimizers, state, ctx.rng("MCMC relocation")))
        counts["perturbed"] = self.noise.perturb(ctx, type(self).__name__)
        return counts

    def refine(self, params: Params, optimizers: Optimizers, state: dict[str, Any], generator: torch.Generator
               ) -> dict[str, int]:
        """One refinement: relocation of the dead, then growth."""
        return {"relocated": self.relocate_dead(params, optimizers, state, generator),
                "added": self.grow(params, optimizers, state, generator)}

    def track_loss(self, state: dict[str, Any], loss: Tensor | None) -> None:
        """Add the step's loss to the automatic cap's current window (:func:`auto_add_loss`)."""
        if loss is None:
            raise StrategyError(f"{type(self).__name__} with cap_max '{AUTO}' reads the training loss: pass "
                                f"loss=<the step's loss, a 0-d tensor> to step_post_backward")
        auto_add_loss(state, loss)

    def without_held_out_views(self) -> tuple["MCMCStrategy", str]:
        """Too few training views to hold some out: the training loss's fall decides the count
        instead (cap_max 'auto', which reads no held-out view)."""
        return replace(self, cap_max=AUTO), f"the training loss's fall (--strategy.cap-max {AUTO})"

    def growth_cap(self, state: dict[str, Any], n: int) -> int:
        """The cap of this refinement's growth: ``cap_max``; for 'validated' the count kept, or,
        while undecided, count_ceiling times the count at the first refinement; for 'auto' the
        count at which the loss stopped falling (no cap while it still falls;
        :func:`auto_close_window`, called once per refinement)."""
        if self.cap_max == VALIDATED:
            if state[COUNT_CAP] is not None:
                return state[COUNT_CAP]
            if state[COUNT_START] is None:
                state[COUNT_START] = n
            return int(math.floor(self.count_ceiling * state[COUNT_START]))
        if self.cap_max != AUTO:
            return self.cap_max
        return auto_close_window(state, n, self.auto_min_drop, self.auto_span, self.auto_patience)

    def growth_count(self, state: dict[str, Any], n: int) -> int:
        """How many to add at this refinement: growth_rate x N, never beyond the cap."""
        return max(0, min(self.growth_cap(state, n), int((1.0 + self.growth_rate) * n)) - n)

    def exploration_summary(self, state: dict[str, Any]) -> dict[str, int]:
        """With cap_max 'auto' or 'validated': ``auto_cap``, the count at which growth stopped (0
        while it grows)."""
        if self.cap_max != AUTO:
            return super().exploration_summary(state)
        return {"auto_cap": int(state[AUTO_CAP] or 0)}

    def dead_mask(self, params: Params) -> Tensor:
        """[N] bool: opacity at or below min_opacity, or not finite (NaN counts as dead)."""
        return ~(torch.sigmoid(params["opacities"].detach().flatten()) > self.min_opacity)

    def relocate_dead(self, params: Params, optimizers: Optimizers, state: dict[str, Any], generator: torch.Generator) -> int:
        """Move dead Gaussians (and rows with non-finite opacity) onto live ones."""
        if num_gaussians(params) == 0:
            return 0
        dead = self.dead_mask(params)
        return row_ops.relocate(params, optimizers, state["stats"], dead, generator, state["binoms"], self.min_opacity)

    def grow(self, params: Params, optimizers: Optimizers, state: dict[str, Any], generator: torch.Generator) -> int:
        """Add growth_rate x N new Gaussians, never beyond the cap (:meth:`growth_count`)."""
        return self.sample_copies(params, optimizers, state, self.growth_count(state, num_gaussians(params)), generator)

    def sample_copies(self, params: Params, optimizers: Optimizers, state: dict[str, Any], n: int,
                      generator: torch.Generator) -> int:
        """Append ``n`` copies of live Gaussians drawn by opacity, with the relocation update."""
        return row_ops.sample_add(params, optimizers, state["stats"], n, generator, state["binoms"], self.min_opacity)
