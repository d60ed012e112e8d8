"""Gradient-branch norms during training: a training callback (``eg-train --grad-branches-every N``)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

from exploregs_plugin.callbacks import TrainingCallback

from .branches import sample_branch_norms
from .sampling import train_problems

if TYPE_CHECKING:
    from exploregs_plugin.pipeline import Pipeline


class ScalarSink(Protocol):
    def scalar(self, tag: str, value: float, step: int) -> None: ...


def pipeline_branch_norms(pipeline: Pipeline, step: int, n_views: int) -> dict[str, float]:
    """Per-view mean gradient norm of each branch (and total) on ``n_views`` evenly spaced
    training views, with the pipeline's loss, background, raster settings and the SH degree of
    ``step``. Reads the state only (see :mod:`.sampling`)."""
    return sample_branch_norms(train_problems(pipeline, n_views, step))


@dataclass
class BranchGradientLogger(TrainingCallback):
    """Logs ``grad_branches/{mean2d,cov,sh,total}`` (and ``grad_branches/ratio_mean2d_cov``)
    every ``every`` steps; ``every`` = 0 switches it off. As a training callback, fields left at
    None come from the trainer's config (``grad_branches_every``, off without tensorboard, and
    ``grad_branches_views``)."""

    every: int | None = None
    views: int | None = None
    serves = ("grad_branches_every",)

    def __post_init__(self) -> None:
        if (self.every is not None and self.every < 0) or (self.views is not None and self.views < 1):
            raise ValueError(f"grad-branch logging needs every >= 0 and views >= 1, got {self.every}, {self.views}")

    def on_train_start(self, trainer: Any) -> None:
        config = trainer.config
        if self.every is None:
            self.every = config.grad_branches_every if config.tensorboard else 0
        if self.views is None:
            self.views = config.grad_branches_views
        self.__post_init__()

    def after_step(self, trainer: Any, step: int, stats: dict[str, Any]) -> None:
        self(trainer.pipeline, step, trainer.logger)

    def __call__(self, pipeline: Pipeline, step: int, sink: ScalarSink | Any) -> dict[str, float] | None:
        """``step``: the number of steps completed. Returns the logged values (None when idle)."""
        if not self.every or step % self.every:
            return None
        norms = pipeline_branch_norms(pipeline, step, self.views or 4)
        for name, value in norms.items():
            sink.scalar(f"grad_branches/{name}", value, step)
        if norms["cov"] > 0:
            sink.scalar("grad_branches/ratio_mean2d_cov", norms["mean2d"] / norms["cov"], step)
        return norms
