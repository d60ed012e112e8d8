"""The Operator contract: one exploration operator, its own config, run by a strategy in order.

A composed strategy (:class:`~exploregs_plugin.strategies.exploration.ExplorationStrategy`) holds
its operators as nested dataclass fields, so each has its own config namespace on the command line
(``--strategy.seeding.n-seed``) and in ``config.yml``; they run in the order of those fields. An
operator is a dataclass with hooks, each with a default, that the strategy calls at fixed points of
Default's step (``owner`` is the strategy, for its refinement window, ``cap_max`` room and split
factor)::

    observe(owner, params, state, view)         # each view, inside the refinement window
    size_prune_factor(owner, step)              # world-size prune threshold, or None (no opinion)
    extra_prune(owner, params, state, step)     # more rows to prune at a refinement step
    explore(owner, ctx)                         # every step, after densification, before the reset
    exploration_summary(state)                  # totals logged at each evaluation

Operators keep their per-Gaussian statistics in ``state["stats"]`` (kept aligned with the rows by
``row_ops``) under names of their own, and draw random numbers only from ``ctx.generator``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar, TypeVar

from torch import Tensor

from .observation import ViewObservation
from .row_ops import Params
from .requirements import merged_requires

if TYPE_CHECKING:  # the strategies hold operators; an operator only reads its owner's settings
    from .base import StepContext
    from .budget import ExplorationBudget
    from .default import DefaultStrategy

OperatorT = TypeVar("OperatorT", bound="Operator")


@dataclass
class Operator:
    """Base class of exploration operators: every hook has a default, so a subclass overrides
    only what it does."""

    requires: ClassVar[frozenset[str]] = frozenset()
    """What the operator needs from the renderer beyond the 2D-mean gradient and radii (the
    names of :data:`~exploregs_plugin.strategies.requirements.REQUIREMENTS`); its strategy asks for it."""
    COUNTS: ClassVar[tuple[str, ...]] = ()
    """Count keys the operator reports on every step (0 when it did nothing), so every step's
    counts have the same keys."""
    BUDGET_FIELDS: ClassVar[dict[str, str]] = {}
    """The operator's fields that the run's exploration budget fills when left at None: field ->
    the ``ExplorationBudget`` value that fills it (Seeding: ``every`` <- ``seed_every``)."""

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        cls.requires = merged_requires(cls, cls.__dict__.get("requires", frozenset()))

    # ----------------------------------------------------------------- configuration
    def deferred_fields(self) -> tuple[str, ...]:
        """Fields that may be None until :meth:`setup` fills them from the budget."""
        return tuple(self.BUDGET_FIELDS)

    def setup(self: OperatorT, budget: ExplorationBudget) -> OperatorT:
        """A copy with the :data:`BUDGET_FIELDS` left at None filled from the run's exploration budget."""
        filled = {name: getattr(budget, value) for name, value in self.BUDGET_FIELDS.items()
                  if getattr(self, name) is None}
        return dataclasses.replace(self, **filled)

    # ----------------------------------------------------------------- hooks
    def observe(self, owner: DefaultStrategy, params: Params, state: dict[str, Any],
                view: ViewObservation) -> dict[str, int]:
        """Read one of the step's views before the Gaussian set changes (inside the window)."""
        return {}

    def size_prune_factor(self, owner: DefaultStrategy, step: int) -> float | None:
        """The world-size prune threshold (fraction of the extent) this operator needs at
        ``step``, or None to leave Default's."""
        return None

    def extra_prune(self, owner: DefaultStrategy, params: Params, state: dict[str, Any],
                    step: int) -> tuple[Tensor | None, dict[str, int]]:
        """More rows to prune at a refinement step: (mask [N] bool or None, counts)."""
        return None, {}

    def explore(self, owner: DefaultStrategy, ctx: StepContext) -> dict[str, int]:
        """The operator's work on every step, after densification and before the opacity reset."""
        return {}

    def exploration_summary(self, state: dict[str, Any]) -> dict[str, int]:
        """Current totals of what the operator explored (not events)."""
        return {}
