"""An operator and a strategy from outside ExploreGS: 3DGS density control under a hard budget.

``OpacityLimit`` is an exploration operator: after each step's densification, if there are more
than ``max_gaussians`` Gaussians, it removes the most transparent ones (through ExploreGS's row_ops, so
Adam moments stay aligned). ``OpacityBudgetStrategy`` composes it after Default's densification;
``SeedSplitUnderBudget`` runs it after Seed+Split's two operators, to show that a plugin operator
composes with the built-in ones.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import torch

from exploregs_plugin.strategies import ExplorationStrategy, Operator, SeedSplitStrategy, row_ops


@dataclass
class OpacityLimit(Operator):
    """Keep at most ``max_gaussians`` Gaussians after each step; the lowest-opacity ones go first."""

    COUNTS = ("budget_pruned",)

    max_gaussians: int = 2000
    """Largest number of Gaussians kept after each step."""

    def explore(self, owner: Any, ctx: Any) -> dict[str, int]:
        n = row_ops.num_gaussians(ctx.params)
        excess = n - self.max_gaussians
        if excess <= 0:
            return {"budget_pruned": 0}
        opacities = ctx.params["opacities"].detach()
        drop = torch.zeros(n, dtype=torch.bool)
        drop[torch.topk(opacities, excess, largest=False).indices] = True
        return {"budget_pruned": row_ops.remove(ctx.params, ctx.optimizers, ctx.state["stats"], drop)}


@dataclass
class OpacityBudgetStrategy(ExplorationStrategy):
    """Default density control that never keeps more than ``limit.max_gaussians`` Gaussians."""

    limit: OpacityLimit = field(default_factory=OpacityLimit)
    """The hard budget, applied after densification on every step."""


@dataclass
class SeedSplitUnderBudget(SeedSplitStrategy):
    """Seed+Split (splitting, then seeding), then the hard budget."""

    limit: OpacityLimit = field(default_factory=OpacityLimit)
    """The hard budget, applied after the two exploration operators."""
