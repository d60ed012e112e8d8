"""The Strategy contract: a dataclass config plus an explicit, torch.save-able state dict.

Call shape (the same as gsplat's, so strategies can be reused across trainers)::

    strategy = SomeStrategy(...).setup(schedule)          # fills None schedule fields
    state = strategy.initialize_state(scene_scale)         # tensors + scalars only
    strategy.check_sanity(params, optimizers)
    # every step:
    strategy.step_pre_backward(params, optimizers, state, step, view)   # each view: retain means2d grad
    loss = loss + strategy.regularization_loss(params)                  # zero unless regularised
    loss.backward(); optimizer.step() for each; zero_grad()
    counts = strategy.step_post_backward(params, optimizers, state, step, views,
                                         lr=means_lr, generator=gen,    # dict[str, int]
                                         loss=step_loss)                # 0-d tensor, optional
    strategy.holds_out_views(state, step)   # keep views out of training (cap_max 'validated')?
    trial = strategy.count_trial_due(state, step, n)    # a CountTrial to run now, or None
    kept = strategy.decide_count(state, step, trial.counts, per_view_psnrs)   # after it
    # at each evaluation:
    strategy.exploration_summary(state)                                  # dict[str, int]

``view`` is one rendered view's :class:`~exploregs_plugin.strategies.observation.ViewObservation` and
``views`` the step's list of them (one per view of the global batch, in order). Every hook has a
default here, so a subclass overrides only what it changes; the pipeline calls each one
unconditionally. ``initialize_state`` takes the scene centre (the mean training-camera
centre) as well as its scale.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any, ClassVar, Literal, TypeVar

import torch
from torch import Tensor

from ..schedule import Schedule
from . import count_rule
from .count_rule import COUNT_CAP, COUNT_NOTE, COUNT_TRIAL, VALIDATED
from .errors import StrategyError
from .observation import ViewObservation, require_views
from .row_ops import Optimizers, Params, num_gaussians
from .requirements import merged_requires

REQUIRED_KEYS = ("means", "scales", "quats", "opacities")
"""Parameter keys every built-in strategy reads."""

StrategyT = TypeVar("StrategyT", bound="Strategy")


@dataclass
class StepContext:
    """Everything one ``step_post_backward`` call hands to a strategy's operators."""

    params: Params
    optimizers: Optimizers
    state: dict[str, Any]
    step: int
    views: list[ViewObservation]
    """The step's rendered views, in the order of the global batch (one at batch 1)."""
    lr: float = 0.0
    generator: torch.Generator | None = None
    loss: Tensor | None = None
    """The step's training loss (a 0-d tensor, the mean over its views of the loss terms, without
    the regularisers), as the pipeline computed it: possibly on the device, so a strategy that
    reads it adds it to its state as a tensor and converts it only when it decides (MCMC's
    ``cap_max auto``, at its refinement steps). None when the caller gave none."""

    def rng(self, who: str) -> torch.Generator:
        """The caller's generator; a clear error when randomness is needed and none was given."""
        return require_generator(self.generator, who)


@dataclass(frozen=True)
class CountTrial:
    """Counts to try the set cut to (each the most significant rows, every one fine-tuned
    ``steps`` steps from the same snapshot, then scored on each held-out view)."""

    counts: list[int]
    steps: int


@dataclass
class Strategy:
    """Base class: shared fields (Gaussian cap, schedule) and the contract's default hooks."""

    cap_max: int | Literal["validated"] | None = None
    """Upper bound on the number of Gaussians; growth stops there. None: no cap. 'validated': a few
    training views are held out, and at the last refinement the trainer tries the set cut to
    count_cuts of its count (the most significant Gaussians), each candidate fine-tuned
    count_trial_steps steps from the same snapshot; the smallest whose held-out PSNR is within
    count_tolerance dB of the best candidate's (per view, with its standard error) is kept and
    the views return to training (eg-train's pipeline runs the trial; docs/strategies.md). A
    capture of fewer than 8 training views trains with :meth:`without_held_out_views` instead."""
    refine_start_iter: int | None = None
    """Refinement runs on steps strictly after this one. None: the run's schedule (refine_start)."""
    refine_stop_iter: int | None = None
    """Refinement (and its statistics) stops at this step. None: the run's schedule."""
    refine_every: int | None = None
    """Refinement interval in steps. None: the run's schedule."""
    reset_every: int | None = None
    """Opacity reset interval in steps. None: the run's schedule."""
    count_cuts: tuple[float, ...] = (1.0, 0.7, 0.5, 0.35, 0.25)
    """cap_max 'validated': the candidates, as fractions of the count at the last refinement
    (steps of about sqrt(2), so that a pick lies within 20% of any count between them)."""
    count_trial_steps: int | None = None
    """cap_max 'validated': fine-tuning steps per candidate before it is scored. None: 1% of the
    run's steps (300 of 30k)."""
    count_tolerance: float = 0.1
    """cap_max 'validated': the largest held-out PSNR deficit (dB, the per-view mean plus its
    standard error) at which a smaller candidate still counts as good as the best."""

    requires: ClassVar[frozenset[str]] = frozenset()
    """What the strategy class needs beyond the 2D-mean gradient and radii, which every
    observation carries: ``VIEW_ERRORS`` (each view's ``ViewObservation.error``: its index,
    camera, target and error map) and ``VISIBILITY_STATS`` (``ViewObservation.visibility``
    [N, 2]: each Gaussian's summed compositing weight alpha T and alpha over the view's pixels).
    The pipeline asks the renderer for :meth:`requirements`."""

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        cls.requires = merged_requires(cls, cls.__dict__.get("requires", frozenset()))

    def requirements(self) -> frozenset[str]:
        """What this strategy needs from the renderer: its class's ``requires`` (a composed
        strategy adds its operators')."""
        return type(self).requires

    def without_held_out_views(self) -> tuple["Strategy", str]:
        """This strategy for a capture too small to hold views out (cap_max 'validated' with
        fewer than ``count_rule.MIN_VIEWS`` training views), and what decides its count then: no
        cap, and the end-of-run cut by significance where the strategy has one (it reads the
        training views only)."""
        without = dataclasses.replace(self, cap_max=None)
        share = without.final_cut_share()
        rule = (f"the end-of-run cut by significance (--strategy.final-weight-share {share:g})" if share > 0
                else "no cap (the growth rule alone)")
        return without, rule

    CAP_WORDS: ClassVar[tuple[str, ...]] = (VALIDATED,)
    """The words cap_max takes besides a count."""

    MORE_GAUSSIANS: ClassVar[str] = "more growth"
    """What lets the count rule try more Gaussians, for the decision line when it keeps the whole set."""

    SCHEDULE_FIELDS: ClassVar[tuple[str, ...]] = (
        "refine_start_iter",
        "refine_stop_iter",
        "refine_every",
        "reset_every",
    )

    def __post_init__(self) -> None:
        if isinstance(self.cap_max, int) and self.cap_max < 0:
            raise StrategyError(f"{type(self).__name__}.cap_max must be >= 0 or None, got {self.cap_max}")
        if isinstance(self.cap_max, str) and self.cap_max not in self.CAP_WORDS:
            words = " or ".join(f"'{w}'" for w in self.CAP_WORDS)
            raise StrategyError(f"cap_max must be a count >= 0, {words}, got {self.cap_max!r}")
        if not self.count_cuts or not all(0.0 < c <= 1.0 for c in self.count_cuts):
            raise StrategyError(f"count_cuts must be fractions in (0, 1], got {self.count_cuts}")
        if not (math.isfinite(self.count_tolerance) and self.count_tolerance >= 0.0):
            raise StrategyError(f"count_tolerance must be >= 0, got {self.count_tolerance}")
        if self.count_trial_steps is not None and self.count_trial_steps < 1:
            raise StrategyError(f"count_trial_steps must be >= 1, got {self.count_trial_steps}")
        for name in ("refine_every", "reset_every"):
            value = getattr(self, name)
            if value is not None and value <= 0:
                raise StrategyError(f"{type(self).__name__}.{name} must be positive, got {value}")

    # ----------------------------------------------------------------- configuration
    def schedule_defaults(self, schedule: Schedule) -> dict[str, int]:
        """Values the run's schedule gives to fields left at None (subclasses may extend)."""
        return {
            "refine_start_iter": schedule.refine_start,
            "refine_stop_iter": schedule.refine_stop,
            "refine_every": schedule.refine_every,
            "reset_every": schedule.reset_every,
            "count_trial_steps": max(1, round(count_rule.TRIAL_SHARE * schedule.max_steps)),
        }

    def setup(self: StrategyT, schedule: Schedule) -> StrategyT:
        """A copy with every None field that the schedule defines filled in."""
        filled = {
            name: value
            for name, value in self.schedule_defaults(schedule).items()
            if getattr(self, name) is None
        }
        return dataclasses.replace(self, **filled)

    def deferred_fields(self) -> tuple[str, ...]:
        """Fields that may be None until :meth:`setup` fills them (subclasses extend)."""
        return self.SCHEDULE_FIELDS

    def require_schedule(self) -> None:
        # a dotted name ("seeding.n_seed") is a field of a nested operator config
        missing = [name for name in self.deferred_fields() if _field_at(self, name) is None]
        if missing:
            raise StrategyError(
                f"{type(self).__name__} has unset schedule fields {missing}: call "
                f"strategy.setup(schedule) (or set them) before training"
            )

    def room(self, n_current: int) -> int:
        """How many Gaussians may still be added under ``cap_max`` (a large number if None, or
        'auto', whose strategy decides its growth itself)."""
        if not isinstance(self.cap_max, int):
            return 1 << 62
        return max(0, self.cap_max - n_current)

    # ----------------------------------------------------------------- contract
    def initialize_state(
        self, scene_scale: float = 1.0, scene_center: Tensor | None = None
    ) -> dict[str, Any]:
        """Running state: ``scene_scale`` (float), ``scene_center`` [3] and ``stats``.

        ``stats`` holds the per-Gaussian statistics (first dimension N) that the ops keep
        aligned with the rows; it starts empty and is filled on first use.
        """
        if not (math.isfinite(scene_scale) and scene_scale > 0.0):
            raise StrategyError(f"initialize_state: scene_scale must be positive and finite, got {scene_scale}")
        center = torch.zeros(3) if scene_center is None else torch.as_tensor(scene_center, dtype=torch.float32).reshape(3)
        state: dict[str, Any] = {"scene_scale": float(scene_scale), "scene_center": center.clone(), "stats": {}}
        if self.cap_max == VALIDATED:
            state.update(count_rule.validated_state())
        return state

    def check_sanity(self, params: Params, optimizers: Optimizers) -> None:
        """Check the parameter/optimizer convention; raise :class:`StrategyError` if broken."""
        missing = [k for k in REQUIRED_KEYS if k not in params]
        if missing:
            raise StrategyError(f"{type(self).__name__}: parameters lack required keys {missing}")
        trainable = {k for k, p in params.items() if p.requires_grad}
        if trainable != set(optimizers.keys()):
            raise StrategyError(
                f"trainable parameters {sorted(trainable)} and optimizers {sorted(optimizers)} "
                f"must have the same keys"
            )
        n = num_gaussians(params)
        for key, p in params.items():
            if p.shape[0] != n:
                raise StrategyError(f"parameter '{key}' has {p.shape[0]} rows, '{next(iter(params))}' has {n}")
        for key, opt in optimizers.items():
            if len(opt.param_groups) != 1 or len(opt.param_groups[0]["params"]) != 1:
                raise StrategyError(f"optimizer '{key}' must have one param group holding one parameter")
            if opt.param_groups[0]["params"][0] is not params[key]:
                raise StrategyError(f"optimizer '{key}' does not hold params['{key}']")

    def step_pre_backward(
        self, params: Params, optimizers: Optimizers, state: dict[str, Any], step: int, view: ViewObservation
    ) -> None:
        """Called after rendering each view, before ``loss.backward()``. Default: nothing."""

    def step_post_backward(
        self,
        params: Params,
        optimizers: Optimizers,
        state: dict[str, Any],
        step: int,
        views: list[ViewObservation],
        lr: float = 0.0,
        generator: torch.Generator | None = None,
        loss: Tensor | None = None,
    ) -> dict[str, int]:
        """Called after the optimizer step; returns counts of what it did (dict[str, int]; a count
        may be a 0-dim integer tensor on the device, which the trainer reads only where it logs,
        so that a step that changes nothing need not wait for the device).

        Checks that the schedule is resolved and ``views`` is a list of observations, and hands
        one :class:`StepContext` to :meth:`post_backward`, which subclasses implement. ``loss`` is
        the step's training loss as a 0-d tensor (:attr:`StepContext.loss`)."""
        self.require_schedule()
        views = require_views(views, f"{type(self).__name__}.step_post_backward")
        return self.post_backward(StepContext(params, optimizers, state, step, views, lr, generator, loss))

    def post_backward(self, ctx: StepContext) -> dict[str, int]:
        """The strategy's work after each optimizer step. Default: nothing."""
        return {}

    def regularization_loss(self, params: Params) -> Tensor:
        """Extra loss term the trainer adds to the photometric loss. Default: 0."""
        return params["means"].new_zeros(())

    def exploration_summary(self, state: dict[str, Any]) -> dict[str, int]:
        """Current totals of what the strategy explored (not events), logged at each evaluation
        and written to metrics.json, e.g. Seeding's ``seeds_alive``. Here: with cap_max
        'validated', ``auto_cap``, the count kept (0 while it is undecided)."""
        if self.cap_max == VALIDATED:
            return {"auto_cap": int(state[COUNT_CAP] or 0)}
        return {}

    def last_refinement(self) -> int:
        """The step of the run's last refinement (the last multiple of refine_every before
        refine_stop_iter), or -1 when the window holds none."""
        last = (self.refine_stop_iter - 1) // self.refine_every * self.refine_every
        return last if last > self.refine_start_iter else -1

    def holds_out_views(self, state: dict[str, Any], step: int) -> bool:
        """Whether the caller keeps a few training views out of training before ``step``, to score
        the candidates of :meth:`count_trial_due` on them. With cap_max 'validated' until the count
        is decided, at the last refinement (or, in a window without refinements, until it
        closes); asked at the start of the run and after every step; once False, the views
        return to training for good."""
        return (self.cap_max == VALIDATED and state[COUNT_CAP] is None
                and step <= max(self.last_refinement(), self.refine_stop_iter - 1))

    def count_trial_due(self, state: dict[str, Any], step: int, n: int) -> CountTrial | None:
        """The count trial the caller should run after this step, or None; ``n`` is the current
        count. eg-train's pipeline runs it (:mod:`exploregs_plugin.engine.count_trial`) and hands the
        scores to :meth:`decide_count`. With cap_max 'validated', at the last refinement while
        undecided: :func:`count_rule.candidate_counts` of ``n``."""
        if self.cap_max != VALIDATED or state[COUNT_CAP] is not None or step != self.last_refinement():
            return None
        return CountTrial(count_rule.candidate_counts(n, self.count_cuts), int(self.count_trial_steps or 1))

    def decide_count(self, state: dict[str, Any], step: int, counts: list[int],
                     per_view: list[list[float]]) -> int:
        """The count to keep, from the trial of :meth:`count_trial_due`'s ``counts``
        (``per_view[i]``: candidate i's PSNR on each held-out view): the one
        :func:`count_rule.pick_count` picks, with why; the caller cuts the set to it."""
        if self.cap_max != VALIDATED:
            raise StrategyError(f"{type(self).__name__} decides no count (cap_max {self.cap_max!r})")
        chosen = counts[count_rule.pick_count(counts, per_view, self.count_tolerance)]
        means = [count_rule.mean_psnr(scores) for scores in per_view]
        state[COUNT_CAP] = chosen
        state[COUNT_TRIAL] = [(int(c), float(m), [float(p) for p in scores])
                              for c, m, scores in zip(counts, means, per_view)]
        tried = ", ".join(f"{c:,}: {m:.2f}" for c, m in zip(counts, means))
        views = len(per_view[0]) if per_view else 0
        state[COUNT_NOTE] = (f"count chosen: {chosen:,} of {max(counts):,} Gaussians (step {step}), the smallest "
                             f"cut within {self.count_tolerance:g} dB of the best on {views} held-out views, per "
                             f"view with its standard error, each cut fine-tuned {self.count_trial_steps} steps "
                             f"(held-out PSNR, dB: {tried}){self._count_edge(chosen, counts, per_view)}")
        return chosen

    def _count_edge(self, chosen: int, counts: list[int], per_view: list[list[float]]) -> str:
        """Where the pick is an end of the candidates, the scene's count may lie beyond them: say
        so, and which field widens the trial (the pick of the smallest cut means every cut scored
        as well as the best; of the whole set, that every cut cost more than the tolerance)."""
        if not count_rule.scored_candidates(per_view):
            return "; no candidate scored a finite PSNR, so the whole set is kept"
        if len(counts) < 2:
            return ""
        if chosen == min(counts):
            return "; the smallest cut tried: the scene may need fewer (a smaller last --strategy.count-cuts)"
        if chosen == max(counts):
            return f"; the whole set: the scene may need more ({self.MORE_GAUSSIANS})"
        return ""

    def count_decision(self, state: dict[str, Any]) -> str:
        """One line that says what count was kept and why, once a rule has decided ('' before, and
        for a strategy without such a rule)."""
        return state.get(COUNT_NOTE, "") if self.cap_max == VALIDATED else ""

    def cut_lines(self, state: dict[str, Any]) -> list[str]:
        """The line of each cut :meth:`final_cut` made so far, in order (the settled cut's, then the
        end-of-run cut's); metrics.json keeps them (``cut_lines``), where ``count_decision`` holds
        the last. The base cuts nothing."""
        return []

    def final_cut_share(self) -> float:
        """The share of the training views' compositing weight whose least significant Gaussians
        :meth:`final_cut` removes after the run's last step (0: none; the base keeps every row)."""
        return 0.0

    def settled_cut_step(self, max_steps: int) -> int | None:
        """The count of steps after which :meth:`final_cut` also runs once, with ``last=False``, so
        that the rest of the run trains only the rows it keeps (None: none; the base cuts nothing)."""
        return None

    def final_cut(self, params: Params, optimizers: Optimizers, state: dict[str, Any], visibility: Tensor,
                  step: int, score_without: Any = None, last: bool = True) -> int:
        """After the last step, before the final evaluation (or, with ``last`` False, after
        ``step`` at :meth:`settled_cut_step`): remove rows by their visibility
        statistics over every training view (``visibility`` [N, 4] float64, ``CUT_COLUMNS``: the
        summed compositing weight, the summed alpha, > 0 where a view drew the row, the peak weight
        and the weight in the view that draws the row most; eg-train's
        pipeline sums them from the training renders of the run's last whole epoch,
        :mod:`exploregs_plugin.engine.final_weights`, or renders them with
        :func:`exploregs_plugin.model.significance.visibility_totals`). Returns
        the rows removed. ``score_without(rows)``, where the caller can render, gives the PSNR of
        each of a fixed list of training views rendered without ``rows`` ([N] bool), to check a cut.
        Default's rule: :class:`DefaultStrategy.final_weight_share` and ``final_cut_tolerance``."""
        return 0


def _field_at(config: Any, dotted: str) -> Any:
    for part in dotted.split("."):
        config = getattr(config, part)
    return config


def require_generator(generator: torch.Generator | None, who: str) -> torch.Generator:
    """The strategies draw random numbers only from the caller's generator."""
    if generator is None:
        raise StrategyError(
            f"{who} needs randomness: pass generator=torch.Generator().manual_seed(seed) to "
            f"step_post_backward"
        )
    return generator
