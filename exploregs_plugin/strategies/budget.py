"""Exploration budgets: the paper's per-step counts, and CPU-scale presets with the same ratios.

The paper trains 30k steps and ends with 1-2.5M Gaussians. Random Splitting splits 20 Gaussians
every step of the densification window (500..15k), about 290k splits in all; Random Seeding adds
20 seeds at each of the ~145 densification steps, about 2.9k seeds, roughly 0.2% of the final
count. A CPU run with tens of thousands of Gaussians keeps those *ratios* of explored to final
primitives instead of the absolute counts:

    total random splits = SPLIT_FRACTION x final Gaussians  (290k / 1.5M = 0.193)
    total seeds         = SEED_FRACTION  x final Gaussians  (0.2%)

spread evenly over the run's densification window (see :func:`scaled_budget`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

PAPER_N_SEED = 20
"""Seeds per seeding step in the paper."""
PAPER_N_SPLIT = 20
"""Random splits per step in the paper."""
PAPER_SPLIT_EVERY = 1
"""The paper splits 'per iteration'."""
PAPER_FINAL_GAUSSIANS = 1_500_000
"""Typical final Gaussian count of the paper's scenes (1-2.5M)."""
PAPER_RANDOM_SPLITS = 290_000
"""Total random splits in a paper run (20 per step over the 14.5k-step window)."""
SPLIT_FRACTION = PAPER_RANDOM_SPLITS / PAPER_FINAL_GAUSSIANS
"""Random splits per final Gaussian (~0.193)."""
SEED_FRACTION = 0.002
"""Seeds per final Gaussian (~0.2%)."""

BUDGET_PRESETS: dict[str, int | None] = {
    "paper": None,
    "cpu-tiny": 2_000,
    "cpu-small": 20_000,
    "cpu-medium": 60_000,
}
"""Preset name -> expected final Gaussian count (None: the paper's per-step counts)."""


BudgetName = Literal["paper", "cpu-tiny", "cpu-small", "cpu-medium"]
"""The preset names, for the CLI (kept equal to the keys of BUDGET_PRESETS)."""


@dataclass(frozen=True)
class ExplorationBudget:
    """Per-step exploration counts and intervals."""

    n_seed: int
    seed_every: int
    n_split: int
    split_every: int


def paper_budget(refine_every: int, views_per_step: int = 1) -> ExplorationBudget:
    """The paper's counts: 20 seeds per densification step, 20 random splits per image seen
    (per step at one view per step; a step of B views splits 20 B)."""
    return ExplorationBudget(PAPER_N_SEED, refine_every, PAPER_N_SPLIT * views_per_step, PAPER_SPLIT_EVERY)


SPREAD_TOLERANCE = 0.05
"""A budget may miss its total by this fraction in exchange for more frequent, smaller events."""


def _spread(total: int, slots: int, base_interval: int) -> tuple[int, int]:
    """(count per event, interval) so that about ``total`` items fall in ``slots`` events.

    Events happen every ``e`` slots (interval ``e * base_interval``) with ``n`` items each,
    realising n * (slots // e) items. The most frequent events (smallest ``e``) whose total is
    within SPREAD_TOLERANCE of ``total`` win, so exploration stays smooth; if none is, the
    closest total wins.
    """
    best = None
    for e in range(1, slots + 1):
        n = max(1, round(total * e / slots))
        error = abs(n * (slots // e) - total)
        if error <= max(1.0, SPREAD_TOLERANCE * total):
            return n, e * base_interval
        if best is None or error < best[0]:
            best = (error, e, n)
    _, e, n = best
    return n, e * base_interval


def scaled_budget(final_gaussians: int, refine_start: int, refine_stop: int, refine_every: int) -> ExplorationBudget:
    """Counts that keep the paper's explored-to-final ratios for a run ending near
    ``final_gaussians`` Gaussians, spread over the densification window."""
    if final_gaussians <= 0 or refine_every <= 0:
        raise ValueError(
            f"scaled_budget: final_gaussians and refine_every must be positive, got "
            f"{final_gaussians}, {refine_every}"
        )
    window = max(1, refine_stop - refine_start)
    n_split, split_every = _spread(max(1, round(SPLIT_FRACTION * final_gaussians)), window, 1)
    n_seed, seed_every = _spread(
        max(1, round(SEED_FRACTION * final_gaussians)), max(1, window // refine_every), refine_every
    )
    return ExplorationBudget(n_seed, seed_every, n_split, split_every)


def resolve_budget(name: str, refine_start: int, refine_stop: int, refine_every: int,
                   views_per_step: int = 1) -> ExplorationBudget:
    """The budget of a preset name for a given densification window (in steps of
    ``views_per_step`` views). The scaled presets fix totals over the window, so they need no
    batch correction; the paper's per-step split count is per image seen."""
    if name not in BUDGET_PRESETS:
        raise ValueError(f"unknown exploration budget '{name}'; known presets: {sorted(BUDGET_PRESETS)}")
    final = BUDGET_PRESETS[name]
    if final is None:
        return paper_budget(refine_every, views_per_step)
    return scaled_budget(final, refine_start, refine_stop, refine_every)
