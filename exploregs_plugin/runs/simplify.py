"""A smaller splat from a trained run: keep the Gaussians that make the training images (the
largest total compositing weight over the training views times the largest weight at one pixel,
:func:`exploregs_plugin.model.significance.cut_order`), and optionally fine-tune what is left.

Removing Gaussians changes T for the ones behind them, so a pruned scene is not exactly the sum of
what is kept; ``finetune`` lets the kept Gaussians take up the slack at the run's final learning
rates, without densification (the strategy is replaced by the contract's do-nothing base).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from exploregs_plugin.engine import count_trial
from exploregs_plugin.model.significance import most_significant, visibility_cut_order
from exploregs_plugin.engine.pipeline import Pipeline
from exploregs_plugin.strategies import row_ops
from exploregs_plugin.strategies.base import Strategy


@dataclass(frozen=True)
class Simplified:
    """What :func:`simplify` did: Gaussians before and after, the share of the training images'
    total compositing weight that the kept ones carried before pruning, and the steps fine-tuned."""

    before: int
    after: int
    kept_weight_share: float
    finetune_steps: int


def finetune(pipeline: Pipeline, step: int, steps: int) -> None:
    """``steps`` training steps of ``pipeline`` at step ``step``'s learning rates and SH degree,
    with no strategy: the set of Gaussians stays as it is (no densification, pruning or noise)."""
    if steps < 0:
        raise ValueError(f"--finetune-steps must be >= 0, got {steps}")
    if steps == 0:
        return
    pipeline.strategy = Strategy().setup(pipeline.schedule)
    centers = torch.stack([camera.camera_center for camera in pipeline.datamanager.train_cameras])
    pipeline.strategy_state = pipeline.strategy.initialize_state(
        scene_scale=pipeline.scene_extent, scene_center=centers.mean(dim=0).to(pipeline.device))
    for _ in range(steps):
        pipeline.train_step(step)
    pipeline.check_finite(step)
    error = pipeline.nonfinite_error()
    if error is not None:
        raise error


def simplify(pipeline: Pipeline, step: int, max_gaussians: int, finetune_steps: int = 0) -> Simplified:
    """Keep the ``max_gaussians`` Gaussians of a loaded run's ``pipeline`` with the largest weight x
    peak (:func:`cut_order`; their Adam moments follow the rows), then fine-tune ``finetune_steps``
    steps; in place."""
    if pipeline.model.parts:
        raise ValueError("--max-gaussians is for static scenes: a dynamic run's Gaussians move with time, "
                         "and one view's weights do not say what every time needs")
    params = pipeline.params
    before = int(params["means"].shape[0])
    totals = count_trial.training_visibility(pipeline)  # the training views, as the count rule's cut
    keep = most_significant(visibility_cut_order(totals), max_gaussians)
    significance = totals[:, 0]
    total = float(significance.sum())
    share = float(significance[keep].sum()) / total if total > 0.0 else 1.0
    row_ops.remove(params, pipeline.optimizers, {}, ~keep)
    finetune(pipeline, step, finetune_steps)
    return Simplified(before, int(params["means"].shape[0]), share, finetune_steps)
