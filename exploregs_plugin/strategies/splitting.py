"""Random Splitting (near side): split Gaussians drawn in proportion to their size.

Every ``split_every`` steps inside the densification window, ``n_split`` Gaussians are drawn
without replacement with probability proportional to their mean (activated) scale, regardless
of their gradient, and split with the common split op (two children from the parent's Gaussian,
scales / 1.6, parent removed).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import torch
from torch import Tensor

from . import row_ops
from .errors import StrategyError
from .exploration import ExplorationStrategy
from .operator_contract import Operator
from .row_ops import Optimizers, Params, num_gaussians

if TYPE_CHECKING:
    from .base import StepContext
    from .default import DefaultStrategy


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


def split_drawn(params: Params, optimizers: Optimizers, stats: dict[str, Tensor], weights: Tensor, n: int,
                generator: torch.Generator, scale_factor: float = 1.6) -> int:
    """Split up to ``n`` distinct rows drawn in proportion to ``weights`` [N] (``row_ops.split``: two
    children from the parent's Gaussian, scales / ``scale_factor``). Returns the number split."""
    idx = draw_rows(weights, n, generator)
    mask = torch.zeros(num_gaussians(params), dtype=torch.bool, device=params["means"].device)
    mask[idx] = True  # distinct rows: len(idx) of them
    return row_ops.split(params, optimizers, stats, mask, generator, scale_factor, count=len(idx))


@dataclass
class RandomSplitting(Operator):
    """Random Splitting: ``n_split`` Gaussians drawn by size and split every ``every`` steps
    inside the densification window."""

    COUNTS = ("random_split",)
    BUDGET_FIELDS = {"n_split": "n_split", "every": "split_every"}

    n_split: int | None = None
    """Gaussians split per splitting step (0 disables). None: from the strategy's budget (paper: 20)."""
    every: int | None = None
    """Splitting interval in steps. None: from the strategy's budget (paper: 1, 'per iteration')."""

    def __post_init__(self) -> None:
        if self.n_split is not None and self.n_split < 0:
            raise StrategyError(f"{type(self).__name__}.n_split must be >= 0, got {self.n_split}")
        if self.every is not None and self.every < 1:
            raise StrategyError(f"{type(self).__name__}.every must be >= 1, got {self.every}")

    def explore(self, owner: DefaultStrategy, ctx: StepContext) -> dict[str, int]:
        split = 0
        if self.n_split and owner.refine_start_iter < ctx.step < owner.refine_stop_iter and ctx.step % self.every == 0:
            split = self.random_split(owner, ctx.params, ctx.optimizers, ctx.state, ctx.rng("random splitting"))
        return {"random_split": split}

    def candidate_weights(self, params: Params, state: dict[str, Any]) -> Tensor:
        """Selection weight of each Gaussian [N]: its mean scale (the paper's rule). Other
        choices of candidates (occlusion-aware splitting) override this."""
        return split_weights(params["scales"])

    def random_split(self, owner: DefaultStrategy, params: Params, optimizers: Optimizers,
                     state: dict[str, Any], generator: torch.Generator) -> int:
        """Split up to n_split Gaussians drawn by size (fewer if N or the owner's cap_max leave
        less room), with the owner's split factor."""
        n = num_gaussians(params)
        budget = min(self.n_split, n, owner.room(n))
        if budget <= 0:
            return 0
        return split_drawn(params, optimizers, state["stats"], self.candidate_weights(params, state), budget,
                           generator, owner.split_scale_factor)


@dataclass
class SplittingStrategy(ExplorationStrategy):
    """Random Splitting on top of 3DGS adaptive density control."""

    splitting: RandomSplitting = field(default_factory=RandomSplitting)
    """Random Splitting (near side)."""
