"""3DGS-MCMC with exploration: a share of each relocation and of each growth goes to explored
positions instead of onto live Gaussians.

MCMC's relocation and growth only exploit: a dead Gaussian moves onto a live one drawn by
opacity, and growth copies live ones the same way. Here, at every refinement, a share
``explore_share`` of the dead rows and of the growth is explored instead (k = floor(share x n +
1/2) of n), split by the weights ``explore_split`` : ``explore_box`` : ``explore_guided`` (largest
remainders, :func:`apportion`) between

- random size-weighted splits (Random Splitting's rule, :func:`~.splitting.split_drawn`),
- seeds uniform in the seed box (Random Seeding's placement, ``seeding.box_seed_rows``; by
  default the cube of the scene extent around the cameras, ``box_mode='cameras'``),
- seeds on the rays of the pixels with the highest recent error, at depths sampled along the ray
  up to the far corner of that box (guided seeding's placement, ``seeding.new_seed_rows``;
  ``--strategy.seeding.guide-power 0`` makes them uniform over the training cameras' frusta).

A relocation removes the k dead rows it explores and adds the explorers (the count is kept); the
other dead rows are relocated as MCMC does. Seeds start at opacity ``explore_opacity``, low
enough to change the image little, above the dead threshold; a seed that explains nothing fades
under MCMC's opacity regulariser, dies and is relocated again at a later refinement. Split
children keep their parent's attributes (a 3DGS split covers the parent's footprint). When an
explorer kind cannot place its share (no error map yet, no live row to split) the rest goes to
MCMC's copies, so the count is MCMC's. With ``explore_share = 0`` it is MCMC, bit for bit. The
defaults, share 1 and splits only, come from a short-run sweep on the built-in scenes
(docs/strategies.md), where splits gained most and seeds little or nothing.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import torch

from . import row_ops
from .base import StepContext
from .errors import StrategyError
from .guided import GuidedSeeding
from .mcmc import MCMCStrategy
from .row_ops import Optimizers, Params, num_gaussians
from .requirements import VIEW_ERRORS
from .seeding import add_seeds
from .splitting import split_drawn, split_weights


def explored_count(n: int, share: float) -> int:
    """How many of ``n`` rows are explored: floor(share x n + 1/2) (rounding half up)."""
    return int(math.floor(share * n + 0.5))


def apportion(k: int, weights: tuple[float, ...]) -> list[int]:
    """``k`` split in proportion to ``weights`` (>= 0) by largest remainders: integers summing to
    k (ties to the earlier weight); all zeros when k <= 0 or every weight is 0."""
    total = float(sum(weights))
    if k <= 0 or total <= 0.0:
        return [0] * len(weights)
    exact = [k * w / total for w in weights]
    counts = [int(math.floor(e)) for e in exact]
    order = sorted(range(len(weights)), key=lambda i: (-(exact[i] - counts[i]), i))
    for i in order[: k - sum(counts)]:
        counts[i] += 1
    return counts


@dataclass
class MCMCExploreStrategy(MCMCStrategy):
    """3DGS-MCMC where a share of every relocation and growth goes to explored positions
    (size-weighted splits, uniform seeds, guided seeds) instead of onto live Gaussians."""

    explore_share: float = 1.0
    """Share of the dead rows relocated and of the Gaussians grown at each refinement that go
    to explored positions (0: MCMC; 1, from a short-run sweep on the built-in scenes,
    docs/strategies.md: all of them)."""
    explore_opacity: float = 0.05
    """Opacity of a new explored seed: low enough to change the image little, above min_opacity
    so it lives until training has judged it."""
    explore_split: float = 1.0
    """Weight of size-weighted random splits among the explorers."""
    explore_box: float = 0.0
    """Weight of seeds uniform in the seed box (``seeding.box_mode``) among the explorers (0 by
    default: in the sweep, seeds gained less than splits, guided seeds lost)."""
    explore_guided: float = 0.0
    """Weight of guided seeds (on the rays of high-error pixels) among the explorers."""
    seeding: GuidedSeeding = field(default_factory=lambda: GuidedSeeding(box_mode="cameras"))
    """Where seeds go: box_mode, box_quantile and min_scale for the box seeds and the guided
    seeds' far bound; guide_* for the guided ones (guide_power 0: uniform over the training
    cameras' frusta). Box 'cameras' by default: MCMC's noise carries transparent Gaussians far
    away, so the box of the centres ('aabb') grows, and with it the seeds' spread, scale and
    noise, without bound. Its schedule, count, probation and opacity fields are not used here
    (MCMC's refinement schedules the explorers, explore_opacity sets their opacity, relocation
    removes the dead)."""

    def __post_init__(self) -> None:
        super().__post_init__()
        if not 0.0 <= self.explore_share <= 1.0:
            raise StrategyError(f"explore_share must be in [0, 1], got {self.explore_share}")
        if not self.min_opacity < self.explore_opacity < 1.0:
            raise StrategyError(f"explore_opacity must lie in (min_opacity, 1) = ({self.min_opacity}, 1), "
                                f"got {self.explore_opacity}")
        weights = self.explore_weights()
        if min(weights) < 0.0 or (self.explore_share > 0.0 and sum(weights) <= 0.0):
            raise StrategyError(f"explore_split, explore_box and explore_guided must be >= 0 with a positive "
                                f"sum, got {weights}")

    def explore_weights(self) -> tuple[float, float, float]:
        return (self.explore_split, self.explore_box, self.explore_guided)

    def requirements(self) -> frozenset[str]:
        """The views' error maps only when guided seeds are drawn (``explore_guided`` > 0)."""
        needs = super().requirements()
        return needs | {VIEW_ERRORS} if self.explore_guided > 0 else needs

    def post_backward(self, ctx: StepContext) -> dict[str, int]:
        if ctx.step < self.refine_stop_iter and self.explore_guided + self.explore_box > 0:
            # the seeds' views (seeds_unseen) and, for guided seeds, each view's error map;
            # without guided seeds the views carry no error map: Random Seeding's observation only
            observe = self.seeding.observe if self.explore_guided > 0 else super(GuidedSeeding, self.seeding).observe
            for view in ctx.views:
                observe(self, ctx.params, ctx.state, view)
        counts = super().post_backward(ctx)
        counts.setdefault("explored", 0)
        return counts

    def refine(self, params: Params, optimizers: Optimizers, state: dict[str, Any], generator: torch.Generator
               ) -> dict[str, int]:
        relocated, explored = self.relocate_exploring(params, optimizers, state, generator)
        n_grow = self.growth_count(state, num_gaussians(params))
        k = explored_count(n_grow, self.explore_share)
        added = self.sample_copies(params, optimizers, state, n_grow - k, generator)
        grown = self.explore_rows(params, optimizers, state, k, generator)
        added += grown + self.sample_copies(params, optimizers, state, k - grown, generator)
        return {"relocated": relocated, "added": added, "explored": explored + grown}

    def relocate_exploring(self, params: Params, optimizers: Optimizers, state: dict[str, Any],
                           generator: torch.Generator) -> tuple[int, int]:
        """MCMC's relocation with ``explore_share`` of the dead rows explored: those rows are
        removed and as many explorers added. Returns (dead rows handled, explorers placed)."""
        if num_gaussians(params) == 0:
            return 0, 0
        dead = self.dead_mask(params)
        n_dead = int(dead.sum())
        k = explored_count(n_dead, self.explore_share)
        if k == 0 or n_dead == num_gaussians(params):  # nothing to explore, or no live row: MCMC's
            return self.relocate_dead(params, optimizers, state, generator), 0
        # the first k dead rows are freed (dead rows are interchangeable); removed before the
        # relocation, so none of them becomes a relocation source
        freed = dead & (torch.cumsum(dead.to(torch.int64), 0) <= k)
        row_ops.remove(params, optimizers, state["stats"], freed)
        moved = self.relocate_dead(params, optimizers, state, generator)
        placed = self.explore_rows(params, optimizers, state, k, generator)
        self.sample_copies(params, optimizers, state, k - placed, generator)
        return moved + k, placed

    def explore_rows(self, params: Params, optimizers: Optimizers, state: dict[str, Any], k: int,
                     generator: torch.Generator) -> int:
        """Add up to ``k`` explorers (splits, then box seeds, then guided seeds, by
        :func:`apportion`); returns how many were placed."""
        n_split, n_box, n_guided = apportion(k, self.explore_weights())
        placed = 0
        if n_split > 0:
            placed += split_drawn(params, optimizers, state["stats"], split_weights(params["scales"]), n_split,
                                  generator)
        for n, place in ((n_box, self.seeding.box_seed_rows), (n_guided, self.seeding.new_seed_rows)):
            rows = place(params, state, n, generator) if n > 0 and num_gaussians(params) > 0 else None
            if rows is not None:
                logit = math.log(self.explore_opacity / (1.0 - self.explore_opacity))
                rows["opacities"] = torch.full_like(rows["opacities"], logit)
                placed += add_seeds(params, optimizers, state["stats"], rows)
        return placed

    def exploration_summary(self, state: dict[str, Any]) -> dict[str, int]:
        """MCMC's, and the explored seeds still in the set (``seeds_alive``) and those no training
        view has seen (``seeds_unseen``)."""
        return {**super().exploration_summary(state), **self.seeding.exploration_summary(state)}
