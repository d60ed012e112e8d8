"""The live viewer as a training callback: built when training starts, fed after every step."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from exploregs_plugin.callbacks import TrainingCallback
from exploregs_plugin.viewer.config import ViewerConfig

if TYPE_CHECKING:  # the server side (viser) loads when a viewer is built, not with the trainer
    from exploregs_plugin.viewer.viewer import Viewer


class ViewerCallback(TrainingCallback):
    """Serves the viewer of ``config`` while the trainer runs (``eg-train --viewer``)."""

    def __init__(self, config: ViewerConfig) -> None:
        self.config = config
        self.viewer: Viewer | None = None

    def on_train_start(self, trainer: Any) -> None:
        self.viewer = self.config.setup(trainer.pipeline, step=trainer.start_step)

    # the hooks below run only after on_train_start built the viewer; close() may come without it
    def before_step(self, trainer: Any, step: int) -> None:
        self.viewer.wait_if_paused(lambda: trainer.stop_requested)

    def after_step(self, trainer: Any, step: int, stats: dict[str, Any]) -> None:
        self.viewer.update(step, stats, stats.get("step_seconds"))

    def on_train_end(self, trainer: Any) -> None:
        self.viewer.finish(trainer.schedule.max_steps, lambda: trainer.stop_requested)

    def close(self) -> None:
        if self.viewer is not None:
            self.viewer.close()
