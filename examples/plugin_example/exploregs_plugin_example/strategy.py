"""A strategy from outside ExploreGS: 3DGS density control under a hard Gaussian budget.

After each step's densification, if there are more than ``budget`` Gaussians, the most
transparent ones are removed (through ExploreGS's ops, so Adam moments stay aligned).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch

from exploregs_plugin.strategies import DefaultStrategy, ops


@dataclass
class OpacityBudgetStrategy(DefaultStrategy):
    """Default density control that never keeps more than ``budget`` Gaussians."""

    budget: int = 2000
    """Largest number of Gaussians kept after each step; the lowest-opacity ones go first."""

    def explore(self, ctx: Any) -> dict[str, int]:
        counts = super().explore(ctx)
        n = ops.num_gaussians(ctx.params)
        excess = n - self.budget
        counts["budget_pruned"] = 0
        if excess > 0:
            opacities = ctx.params["opacities"].detach()
            drop = torch.zeros(n, dtype=torch.bool)
            drop[torch.topk(opacities, excess, largest=False).indices] = True
            counts["budget_pruned"] = ops.remove(ctx.params, ctx.optimizers, ctx.state["stats"], drop)
        return counts
