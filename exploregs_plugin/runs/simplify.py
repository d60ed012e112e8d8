"""A smaller splat from a trained run: keep the Gaussians that make the training images, and
optionally fine-tune what is left.

Significance of Gaussian j is its total compositing weight over every pixel of every training
view,

    S_j = sum_views sum_pixels alpha_j(p) T_j(p),        T_j(p) = prod_{i before j} (1 - alpha_i(p)),

the share of the rendered training images that it paints (sum_j S_j + sum_p T_final(p) = the
number of pixels). It is what the usual proxy, opacity x volume x pixels covered, estimates:
alpha_j(p) already holds the opacity and the footprint, and T_j(p) adds what that proxy misses,
that a Gaussian hidden behind others paints nothing. The renderer computes these sums when asked
(``RasterSettings.visibility_stats``, the sums the occlusion-aware strategies read), in the same
pass as the image, on every backend that has them.

Removing Gaussians changes T for the ones behind them, so a pruned scene is not exactly the sum of
what is kept; ``finetune`` lets the kept Gaussians take up the slack at the run's final learning
rates, without densification (the strategy is replaced by the contract's do-nothing base).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Iterable, Mapping

import torch
from torch import Tensor

from exploregs_plugin.cameras import Camera
from exploregs_plugin.model.gaussians import render_params
from exploregs_plugin.pipeline import Pipeline
from exploregs_plugin.rasterizer import RasterSettings
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


@torch.no_grad()
def blend_weight_totals(params: Mapping[str, Tensor], cameras: Iterable[Camera], settings: RasterSettings | None,
                        background: Tensor | None = None) -> Tensor:
    """[N] float64: S_j = sum over ``cameras`` and their pixels of alpha_j T_j (see the module).

    Rendered at SH degree 0: the weights do not depend on colour, and degree 0 is the cheapest."""
    settings = replace(settings or RasterSettings(), visibility_stats=True)
    means = params["means"]
    totals = torch.zeros(means.shape[0], dtype=torch.float64, device=means.device)
    for camera in cameras:
        _, _, _, info = render_params(params, camera, 0, background, settings)
        totals += info["visibility"][:, 0].to(torch.float64)
    return totals


def most_significant(significance: Tensor, count: int) -> Tensor:
    """[N] bool: the ``count`` rows of largest significance. Ties go to the lower index (a stable
    sort), so the choice is the same on every thread count and backend that gives the same sums."""
    n = significance.shape[0]
    if count < 1:
        raise ValueError(f"--max-gaussians must be >= 1, got {count}")
    keep = torch.zeros(n, dtype=torch.bool, device=significance.device)
    if count >= n:
        return keep.fill_(True)
    order = torch.sort(significance, descending=True, stable=True).indices
    keep[order[:count]] = True
    return keep


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
    """Keep the ``max_gaussians`` most significant Gaussians of a loaded run's ``pipeline`` (its
    Adam moments follow the rows), then fine-tune ``finetune_steps`` steps; in place."""
    model, dm = pipeline.model, pipeline.datamanager
    if model.parts:
        raise ValueError("--max-gaussians is for static scenes: a dynamic run's Gaussians move with time, "
                         "and one view's weights do not say what every time needs")
    params = pipeline.params
    before = int(params["means"].shape[0])
    significance = blend_weight_totals({k: v.detach() for k, v in params.items()}, dm.train_cameras,
                                       model.config.raster, pipeline.background)
    keep = most_significant(significance, max_gaussians)
    total = float(significance.sum())
    share = float(significance[keep].sum()) / total if total > 0.0 else 1.0
    row_ops.remove(params, pipeline.optimizers, {}, ~keep)
    finetune(pipeline, step, finetune_steps)
    return Simplified(before, int(params["means"].shape[0]), share, finetune_steps)
