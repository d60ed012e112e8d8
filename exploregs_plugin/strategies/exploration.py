"""Default's densification plus an ordered list of exploration operators, sharing one budget.

A composed strategy declares its operators as dataclass fields whose values are
:class:`~exploregs_plugin.strategies.operator_contract.Operator` configs; they run in the order of those
fields (the order of ``--help`` and ``config.yml``), each with its own namespace
(``--strategy.seeding.n-seed``). Seed+Split, for example, is::

    @dataclass
    class SeedSplitStrategy(ExplorationStrategy):
        splitting: RandomSplitting = field(default_factory=RandomSplitting)
        seeding: RandomSeeding = field(default_factory=RandomSeeding)

so on a step where both fire, Random Splitting runs first, then seeds are added (fresh seeds are
not split in the step that creates them). A new composition is a new class with other fields; a
new operator is a subclass of ``Operator`` (docs/strategies.md).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, TypeVar

from torch import Tensor

from ..schedule import Schedule
from .base import StepContext
from .budget import BUDGET_PRESETS, BudgetName, resolve_budget
from .default import DefaultStrategy
from .observation import ViewObservation
from .operator_contract import Operator
from .row_ops import Params

ExplorationT = TypeVar("ExplorationT", bound="ExplorationStrategy")


def add_counts(total: dict[str, int], more: dict[str, int]) -> dict[str, int]:
    """``total`` with ``more`` added key by key (in place; returned for chaining)."""
    for key, value in more.items():
        total[key] = total.get(key, 0) + value
    return total


# How a composed strategy runs its operators at Default's hooks. Functions, so that a strategy
# for another trainer (gsplat's: integrations/into_gsplat.py) composes them exactly as ours does.
def operator_fields(strategy: Any) -> list[tuple[str, Operator]]:
    """(field name, operator) for every operator field of the dataclass ``strategy``, in the
    order they run."""
    return [(f.name, getattr(strategy, f.name)) for f in dataclasses.fields(strategy)
            if isinstance(getattr(strategy, f.name), Operator)]


def first_size_prune_factor(operators: list[tuple[str, Operator]], owner: Any, step: int) -> float | None:
    """The world-size prune factor of the first operator with an opinion (Seeding relaxes it
    while it is active), or None when none has one."""
    for _, op in operators:
        factor = op.size_prune_factor(owner, step)
        if factor is not None:
            return factor
    return None


def operators_extra_prune(operators: list[tuple[str, Operator]], owner: Any, params: Params, state: dict[str, Any],
                          step: int, mask: Tensor | None, counts: dict[str, int]) -> tuple[Tensor | None, dict[str, int]]:
    """``mask`` or-ed with every operator's extra rows to prune at a refinement step (None: no
    row), their counts added to ``counts``."""
    for _, op in operators:
        more, op_counts = op.extra_prune(owner, params, state, step)
        add_counts(counts, op_counts)
        if more is not None:
            mask = more if mask is None else mask | more
    return mask, counts


def operators_summary(operators: list[tuple[str, Operator]], state: dict[str, Any]) -> dict[str, int]:
    """The operators' current totals (Random Seeding's ``seeds_alive``, ...)."""
    summary: dict[str, int] = {}
    for _, op in operators:
        summary.update(op.exploration_summary(state))
    return summary


@dataclass
class ExplorationStrategy(DefaultStrategy):
    """3DGS adaptive density control with exploration operators, run in the order of their fields."""

    budget: BudgetName = "paper"
    """Exploration budget preset for the operators' counts and intervals left at None: 'paper' (20
    seeds per densification step, 20 random splits per step) or a CPU preset keeping the paper's
    explored-to-final ratios for an expected final count: 'cpu-tiny' (2k), 'cpu-small' (20k),
    'cpu-medium' (60k)."""

    def __post_init__(self) -> None:
        if self.budget not in BUDGET_PRESETS:
            raise ValueError(f"unknown exploration budget '{self.budget}'; known presets: {sorted(BUDGET_PRESETS)}")
        super().__post_init__()

    def operators(self) -> list[tuple[str, Operator]]:
        """(field name, operator) for every operator field, in the order they run."""
        return operator_fields(self)

    # ----------------------------------------------------------------- configuration
    def setup(self: ExplorationT, schedule: Schedule) -> ExplorationT:
        """Schedule fields filled (Default's), then each operator's budget fields, from one
        budget resolved for the filled densification window."""
        filled = super().setup(schedule)
        budget = resolve_budget(filled.budget, filled.refine_start_iter, filled.refine_stop_iter,
                                filled.refine_every, schedule.views_per_step)
        return dataclasses.replace(filled, **{name: op.setup(budget) for name, op in filled.operators()})

    def deferred_fields(self) -> tuple[str, ...]:
        return super().deferred_fields() + tuple(
            f"{name}.{field}" for name, op in self.operators() for field in op.deferred_fields())

    def requirements(self) -> frozenset[str]:
        return frozenset().union(super().requirements(), *(type(op).requires for _, op in self.operators()))

    # ----------------------------------------------------------------- Default's hooks, per operator
    def observe(self, params: Params, state: dict[str, Any], view: ViewObservation) -> dict[str, int]:
        counts = super().observe(params, state, view)
        for _, op in self.operators():
            add_counts(counts, op.observe(self, params, state, view))
        return counts

    def size_prune_factor(self, step: int) -> float:
        factor = first_size_prune_factor(self.operators(), self, step)
        return super().size_prune_factor(step) if factor is None else factor

    def extra_prune(self, params: Params, state: dict[str, Any], step: int) -> tuple[Tensor | None, dict[str, int]]:
        mask, counts = super().extra_prune(params, state, step)
        return operators_extra_prune(self.operators(), self, params, state, step, mask, counts)

    def explore(self, ctx: StepContext) -> dict[str, int]:
        counts = super().explore(ctx)
        for _, op in self.operators():
            add_counts(counts, op.explore(self, ctx))
        return counts

    def post_backward(self, ctx: StepContext) -> dict[str, int]:
        counts = super().post_backward(ctx)
        for _, op in self.operators():  # the same keys on every step, not only when an operator fired
            for key in op.COUNTS:
                counts.setdefault(key, 0)
        return counts

    def exploration_summary(self, state: dict[str, Any]) -> dict[str, int]:
        return {**super().exploration_summary(state), **operators_summary(self.operators(), state)}
