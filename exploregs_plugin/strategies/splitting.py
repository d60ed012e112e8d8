"""Random Splitting (near side): split Gaussians drawn in proportion to their size.

Every ``split_every`` steps inside the densification window, ``n_split`` Gaussians are drawn
without replacement with probability proportional to their mean (activated) scale, regardless
of their gradient, and split with the common split op (two children from the parent's Gaussian,
scales / 1.6, parent removed).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from . import ops
from .base import StepContext, StrategyError
from .budget import BudgetMixin
from .default import DefaultStrategy
from .ops import Optimizers, Params, num_gaussians


def split_weights(log_scales: Tensor) -> Tensor:
    """Selection weight of each Gaussian: its mean activated scale; 0 for non-finite rows. [N]"""
    w = torch.exp(log_scales.detach()).mean(dim=-1)
    return torch.where(torch.isfinite(w), w, torch.zeros_like(w))


def sample_split_indices(log_scales: Tensor, n: int, generator: torch.Generator) -> Tensor:
    """Draw up to ``n`` distinct rows with probability proportional to mean scale: [m] long.

    m = min(n, number of rows with a positive weight): without replacement there cannot be
    more distinct picks than candidates.
    """
    return draw_rows(split_weights(log_scales), n, generator)


def draw_rows(weights: Tensor, n: int, generator: torch.Generator) -> Tensor:
    """Up to ``n`` distinct rows drawn with probability proportional to ``weights`` [N]: [m] long,
    m = min(n, rows with a positive weight)."""
    m = min(n, int((weights > 0).sum()))
    if m <= 0:
        return torch.zeros(0, dtype=torch.long, device=weights.device)
    return torch.multinomial(weights, m, replacement=False, generator=generator)


@dataclass
class SplittingMixin(BudgetMixin, DefaultStrategy):
    """Random Splitting operator; compose it in front of :class:`DefaultStrategy`."""

    n_split: int | None = None
    """Gaussians split per splitting step (0 disables). None: from `budget` (paper: 20)."""
    split_every: int | None = None
    """Splitting interval in steps. None: from `budget` (paper: 1, 'per iteration')."""

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.n_split is not None and self.n_split < 0:
            raise StrategyError(f"n_split must be >= 0, got {self.n_split}")
        if self.split_every is not None and self.split_every < 1:
            raise StrategyError(f"split_every must be >= 1, got {self.split_every}")

    def deferred_fields(self) -> tuple[str, ...]:
        return super().deferred_fields() + ("n_split", "split_every")

    def explore(self, ctx: StepContext) -> dict[str, int]:
        counts = super().explore(ctx)
        counts["random_split"] = 0
        if (
            self.n_split
            and self.refine_start_iter < ctx.step < self.refine_stop_iter
            and ctx.step % self.split_every == 0
        ):
            counts["random_split"] = self.random_split(ctx.params, ctx.optimizers, ctx.state, ctx.rng("random splitting"))
        return counts

    def split_candidate_weights(self, params: Params, state: dict[str, Any]) -> Tensor:
        """Selection weight of each Gaussian [N]: its mean scale (the paper's rule). Other
        choices of candidates (occlusion-aware splitting) override this."""
        return split_weights(params["scales"])

    def random_split(
        self, params: Params, optimizers: Optimizers, state: dict[str, Any], generator: torch.Generator
    ) -> int:
        """Split up to n_split Gaussians drawn by size (fewer if N or cap_max leave less room)."""
        n = num_gaussians(params)
        budget = min(self.n_split, n, self.room(n))
        if budget <= 0:
            return 0
        idx = draw_rows(self.split_candidate_weights(params, state), budget, generator)
        mask = torch.zeros(n, dtype=torch.bool, device=params["means"].device)
        mask[idx] = True
        return ops.split(params, optimizers, state["stats"], mask, generator, self.split_scale_factor)


@dataclass
class SplittingStrategy(SplittingMixin, DefaultStrategy):
    """Random Splitting on top of 3DGS adaptive density control."""
