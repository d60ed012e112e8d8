"""A short training run made by an analysis command, stopping to probe at chosen iterations."""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Callable

from exploregs_plugin.callbacks import TrainingCallback
from exploregs_plugin.engine.pipeline import Pipeline
from exploregs_plugin.engine.trainer import Trainer, TrainerConfig


@dataclass
class TrainSpec:
    """A short training run made by an analysis command (when no --run is given)."""

    method: str = "exploregs-default"
    """Method to train (see eg-train --help)."""
    data: str = "builtin:default"
    """Dataset: builtin:NAME, a COLMAP folder or a transforms.json folder."""
    data_factor: int | None = None
    """Image downscale factor (unset: the datamanager's default)."""
    max_steps: int = 300
    """Training steps."""
    seed: int = 0
    """Run seed."""
    device: str = "auto"
    """Where to train, or to load --run: auto (CUDA when available, else CPU), cpu, cuda or cuda:N."""

    def trainer_config(self, run_dir: Path) -> TrainerConfig:
        from exploregs_plugin.method_configs import get_method

        base = get_method(self.method).config
        return replace(base, data=self.data, data_factor=self.data_factor, max_steps=self.max_steps,
                       seed=self.seed, device=self.device, run_dir=run_dir, quiet=True, tensorboard=False, eval_count=1,
                       save_eval_images=False, checkpoint_every=max(self.max_steps, 1))  # fmt: skip


Probe = Callable[[Pipeline, int], None]


def train_and_probe(config: TrainerConfig, steps: list[int], probe: Probe) -> Trainer:
    """Train ``config`` and call ``probe(pipeline, step)`` after ``step`` steps for each listed step
    (0 = before training); finishes with an evaluation, metrics.json and a final checkpoint, so
    the folder is an ordinary run that ``--run`` accepts."""
    trainer = Trainer(config, callbacks=[ProbeCallback(probe, steps)])
    trainer.train()
    return trainer


class ProbeCallback(TrainingCallback):
    """Calls ``probe(pipeline, step)`` when ``step`` steps are completed, for each listed step
    (0 = before the first step). Probes read the state only (see :mod:`.sampling`)."""

    def __init__(self, probe: Probe, steps: list[int]) -> None:
        self.probe, self.steps = probe, set(steps)

    def on_train_start(self, trainer: Any) -> None:
        if trainer.start_step in self.steps:
            self.probe(trainer.pipeline, trainer.start_step)

    def after_step(self, trainer: Any, step: int, stats: dict[str, Any]) -> None:
        if step in self.steps:
            self.probe(trainer.pipeline, step)
