"""The paired cut that decides a strategy's count during training (MCMC's ``cap_max 'validated'``).

When the strategy asks (:meth:`Strategy.count_trial_due`), the pipeline tries the set cut to each
candidate count: the rows of largest weight x peak (:func:`exploregs_plugin.model.significance.visibility_cut_order`,
over the training views still trained on), fine-tuned ``steps`` steps at the step's learning rates with no
densification, then scored on every held-out view. Every candidate starts from the same snapshot
and draws the same views in the same order, so two candidates differ in their count alone: the
comparison is paired, and the held-out views' per-view differences measure the count's cost with
the scene's own noise taken out. Afterwards the pipeline is restored to the snapshot, bit for bit
(parameters, Adam, the strategy's state, the generator, the view order), so the run goes on as
if the trial had not been made, and a run resumed from before it makes the same trial.
"""

from __future__ import annotations

import copy
from typing import Any

from torch import Tensor

from exploregs_plugin.model.significance import most_significant, visibility_cut_order, visibility_totals
from exploregs_plugin.engine.nonfinite import NonFiniteWatch
from exploregs_plugin.strategies import row_ops
from exploregs_plugin.strategies.base import CountTrial, Strategy

Pipeline = Any
"""The :class:`exploregs_plugin.engine.pipeline.Pipeline` the trial runs on (which imports this module)."""


class HoldingStrategy(Strategy):
    """The trial's stand-in strategy: it changes nothing and keeps the held-out views out."""

    def holds_out_views(self, state: dict[str, Any], step: int) -> bool:
        return True


def training_visibility(pipeline: Pipeline) -> Tensor:
    """[N, 4] float64 (``CUT_COLUMNS``): each Gaussian's compositing weight and alpha, summed over the
    training views that are still trained on (a held-out view must not choose what is kept), its
    peak weight and its weight in the view that needs it most; one pass."""
    held = set(pipeline.datamanager.held_out)
    return views_visibility(pipeline, [i for i in range(len(pipeline.datamanager.train_cameras)) if i not in held])


def views_visibility(pipeline: Pipeline, indices: list[int]) -> Tensor:
    """:func:`training_visibility` over these training views only (one render each)."""
    cameras = [pipeline.datamanager.train_cameras[i] for i in indices]
    params = {k: v.detach() for k, v in pipeline.params.items()}
    return visibility_totals(params, cameras, pipeline.model.config.raster, pipeline.background)


def cut_scores(pipeline: Pipeline) -> Tensor:
    """[N] float64: the order in which a cut keeps the rows (the largest first): weight x peak over
    the training views (:func:`~exploregs_plugin.model.significance.visibility_cut_order` of
    :func:`training_visibility`)."""
    return visibility_cut_order(training_visibility(pipeline))


def cut(pipeline: Pipeline, weights: Tensor, count: int, stats: dict[str, Tensor]) -> None:
    """Keep the ``count`` rows of largest ``weights`` (:func:`cut_scores`; their Adam moments and
    ``stats`` follow)."""
    keep = most_significant(weights, count)
    row_ops.remove(pipeline.params, pipeline.optimizers, stats, ~keep)


def paired_cut(pipeline: Pipeline, step: int, counts: list[int], steps: int) -> tuple[list[list[float]], Tensor]:
    """Each candidate's PSNR on every held-out view (in the datamanager's order), and the
    scores the cuts used (:func:`cut_scores`); the pipeline is left as it was. Each candidate trains under its
    own non-finite watch: one whose loss or parameters went non-finite scores NaN on every view
    (so :func:`count_rule.pick_count` never keeps it), and the run's own watch, which the trainer
    reads and raises on, never sees a candidate that is thrown away."""
    if pipeline.model.parts:
        raise ValueError("a count decided by a paired cut is for static scenes: a dynamic model's Gaussians move "
                         "with time")
    if not pipeline.datamanager.held_out:
        raise ValueError(f"{type(pipeline.strategy).__name__} asked for a count trial with no views held out")
    snapshot = copy.deepcopy(pipeline.state_dict())
    strategy = pipeline.strategy
    weights = cut_scores(pipeline)
    stand_in = HoldingStrategy().setup(pipeline.schedule)
    run_watch = pipeline.nonfinite
    scores: list[list[float]] = []
    try:
        for count in counts:
            pipeline.load_state_dict(copy.deepcopy(snapshot))  # the same start for every candidate
            pipeline.strategy = stand_in
            pipeline.strategy_state = stand_in.initialize_state(pipeline.scene_extent)
            pipeline.nonfinite = NonFiniteWatch()
            cut(pipeline, weights, count, {})
            for _ in range(steps):
                pipeline.train_step(step)
            views = pipeline.held_out_psnrs(step)
            scores.append(views if pipeline.nonfinite_error() is None else [float("nan")] * len(views))
    finally:
        pipeline.strategy, pipeline.nonfinite = strategy, run_watch
        pipeline.load_state_dict(snapshot)
    return scores, weights


def decide(pipeline: Pipeline, step: int, trial: CountTrial) -> int:
    """Run ``trial``, let the strategy pick, and cut the live set to the pick; returns the count kept."""
    scores, weights = paired_cut(pipeline, step, trial.counts, trial.steps)
    kept = pipeline.strategy.decide_count(pipeline.strategy_state, step, trial.counts, scores)
    cut(pipeline, weights, kept, pipeline.strategy_state.get("stats", {}))
    return kept
