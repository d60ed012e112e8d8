"""Which views and iterations a diagnostic samples.

Probing never touches the training state: views are read with ``train_item`` (not
``next_train``, which would advance the camera order), gradients go to leaf copies of the means,
and nothing draws from the run's random generator, so a probed run trains exactly like an
unprobed one. This module imports neither the trainer nor the pipeline, so the trainer can
import the training-time logger built on it.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from torch import Tensor

from exploregs_plugin.cameras import Camera

from .branches import ViewProblem, training_loss

if TYPE_CHECKING:
    from exploregs_plugin.engine.pipeline import Pipeline


def evenly_spaced(count: int, total: int) -> list[int]:
    """``count`` indices spread evenly over range(total) (all of them when count >= total)."""
    if total <= 0:
        raise ValueError("there is nothing to sample from (0 items)")
    if count <= 0:
        raise ValueError(f"the number of samples must be positive, got {count}")
    if count >= total:
        return list(range(total))
    return sorted({round(i * (total - 1) / max(count - 1, 1)) for i in range(count)})


def probe_steps(max_steps: int, every: int) -> list[int]:
    """Iterations (steps completed) at which to probe: 0, every, 2 every, ..., and max_steps."""
    if every <= 0:
        raise ValueError(f"--every must be positive, got {every}")
    steps = list(range(0, max_steps + 1, every))
    if steps[-1] != max_steps:
        steps.append(max_steps)
    return steps


def train_views(pipeline: Pipeline, count: int) -> list[tuple[Camera, Tensor]]:
    """``count`` evenly spaced training views as (camera, target image [H, W, 3])."""
    dm = pipeline.datamanager
    return [dm.train_item(i)[:2] for i in evenly_spaced(count, len(dm.train_cameras))]




def pipeline_view(pipeline: Pipeline, camera: Camera, target: Tensor, step: int) -> ViewProblem:
    """The loss of one view as the pipeline trains it at ``step``: its parameters, SH degree,
    photometric loss, background and raster settings. target: [H, W, 3]."""
    return ViewProblem(pipeline.params, camera, target, pipeline.sh_degree_at(step),
                       training_loss(pipeline.config.ssim_lambda), pipeline.datamanager.background,
                       pipeline.model.config.raster)  # fmt: skip


def train_problems(pipeline: Pipeline, count: int, step: int) -> list[ViewProblem]:
    """:func:`pipeline_view` of ``count`` evenly spaced training views."""
    return [pipeline_view(pipeline, camera, target, step) for camera, target in train_views(pipeline, count)]
