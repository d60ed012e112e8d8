"""Gradient-branch norms during training: a training callback, and the method that logs them
live to tensorboard (``eg-train exploregs-grad-branches --strategy NAME --grad-branches-every N``).

The diagnostic lives with the analysis, not in the core trainer: ``GradBranchesTrainerConfig``
is a TrainerConfig variant whose ``callbacks()`` adds the logger, so its runs (resumes included)
log the curves, and the core config has no field for it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

from exploregs_plugin.callbacks import TrainingCallback
from exploregs_plugin.method_configs import as_variant, default_variant
from exploregs_plugin.engine.trainer import TrainerConfig

from .branches import sample_branch_norms
from .sampling import train_problems

if TYPE_CHECKING:
    from exploregs_plugin.engine.pipeline import Pipeline


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
    every ``every`` steps, averaged over ``views`` evenly spaced training views; ``every`` = 0
    switches it off."""

    every: int = 0
    views: int = 4

    def __post_init__(self) -> None:
        if self.every < 0 or self.views < 1:
            raise ValueError(f"grad-branch logging needs every >= 0 and views >= 1, got {self.every}, {self.views}")

    def after_step(self, trainer: Any, step: int, stats: dict[str, Any]) -> None:
        self(trainer.pipeline, step, trainer.logger)

    def __call__(self, pipeline: Pipeline, step: int, sink: ScalarSink | Any) -> dict[str, float] | None:
        """``step``: the number of steps completed. Returns the logged values (None when idle)."""
        if not self.every or step % self.every:
            return None
        norms = pipeline_branch_norms(pipeline, step, self.views)
        for name, value in norms.items():
            sink.scalar(f"grad_branches/{name}", value, step)
        if norms["cov"] > 0:
            sink.scalar("grad_branches/ratio_mean2d_cov", norms["mean2d"] / norms["cov"], step)
        return norms


@dataclass
class GradBranchesTrainerConfig(TrainerConfig):
    """A training run that also logs the position gradient's branches to tensorboard."""

    grad_branches_every: int = 100
    """Every this many steps, log the position gradient's norm through each branch (2D mean, 2D
    covariance, SH direction) as grad_branches/* in tensorboard (0 = off; one extra render and
    backward per view; docs/analysis.md)."""
    grad_branches_views: int = 4
    """Training views (evenly spaced) averaged at each --grad-branches-every step."""

    def callbacks(self) -> list[TrainingCallback]:
        every = self.grad_branches_every if self.tensorboard else 0  # the curves go to tensorboard
        return super().callbacks() + [BranchGradientLogger(every, self.grad_branches_views)]


__getattr__ = default_variant(
    "grad_branches_method", "exploregs-grad-branches",
    "3DGS density control that logs the position gradient's branches to tensorboard (--grad-branches-every; "
    "the Blur-Trap diagnostic, live).",
    lambda config: as_variant(GradBranchesTrainerConfig, config),
)
