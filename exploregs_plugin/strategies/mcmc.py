"""3DGS-MCMC (Kheradmand et al. 2024) on CPU.

Every ``refine_every`` steps inside the refinement window: dead Gaussians (opacity <=
``min_opacity``) are relocated onto live ones drawn in proportion to opacity, with the paper's
opacity/scale update (:mod:`.relocation`); then the set grows by ``growth_rate`` (5%) of its size,
by sampling new copies the same way, up to ``cap_max``. After every step the positions get the
opacity-gated, covariance-shaped noise (isotropic, or along the camera ray in 'ray' mode). The
paper's L1 regularisers on opacity and scale come back from :meth:`MCMCStrategy.regularization_loss`
for the trainer to add to its loss.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor

from ..schedule import Schedule
from . import ops
from .base import StepContext, Strategy, StrategyError
from .ops import Optimizers, Params, num_gaussians
from .perturbation import PositionNoise
from .relocation import N_MAX, binomial_table

MCMC_STOP_FRACTION = 25_000 / 30_000
"""3DGS-MCMC refines until step 25k of 30k; a run of any length stops at the same fraction."""


@dataclass
class MCMCStrategy(Strategy):
    """3DGS-MCMC: relocation of dead Gaussians, 5% growth to cap_max, noise after every step."""

    cap_max: int | None = 30_000
    """Largest number of Gaussians (required for MCMC; the paper uses 1-3M on GPU)."""
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

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.cap_max is None:
            raise StrategyError("MCMCStrategy needs cap_max: its 5% growth per refinement is bounded only by it")
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
        if self.refine_start_iter < step < self.refine_stop_iter and step % self.refine_every == 0:
            gen = ctx.rng("MCMC relocation")
            counts["relocated"] = self.relocate_dead(params, optimizers, state, gen)
            counts["added"] = self.grow(params, optimizers, state, gen)
        counts["perturbed"] = self.noise.perturb(ctx, type(self).__name__)
        return counts

    def relocate_dead(self, params: Params, optimizers: Optimizers, state: dict[str, Any], generator: torch.Generator) -> int:
        """Move dead Gaussians (and rows with non-finite opacity) onto live ones."""
        if num_gaussians(params) == 0:
            return 0
        opacity = torch.sigmoid(params["opacities"].detach().flatten())
        dead = ~(opacity > self.min_opacity)  # NaN counts as dead
        return ops.relocate(params, optimizers, state["stats"], dead, generator, state["binoms"], self.min_opacity)

    def grow(self, params: Params, optimizers: Optimizers, state: dict[str, Any], generator: torch.Generator) -> int:
        """Add growth_rate x N new Gaussians, never beyond cap_max."""
        n = num_gaussians(params)
        target = min(self.cap_max, int((1.0 + self.growth_rate) * n))
        return ops.sample_add(
            params, optimizers, state["stats"], max(0, target - n), generator, state["binoms"], self.min_opacity
        )
