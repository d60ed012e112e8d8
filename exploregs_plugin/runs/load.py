"""Loading a finished (or interrupted) run back: config, data, trained Gaussians."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from exploregs_plugin.io.config_files import load_config
from exploregs_plugin.runtime.device import resolve_device
from exploregs_plugin.io.checkpoint import load_run_checkpoint
from exploregs_plugin.engine.pipeline import Pipeline
from exploregs_plugin.engine.trainer import CONFIG_NAME, TrainerConfig


@dataclass
class LoadedRun:
    run_dir: Path
    checkpoint: Path
    step: int
    config: TrainerConfig
    pipeline: Pipeline


def load_run(path: Path, device: str = "auto") -> LoadedRun:
    """``path``: a run folder (latest checkpoint) or one checkpoint file inside it; the run's
    tensors are put on ``device`` (auto, cpu, cuda, cuda:N), whatever device trained it. A
    newest checkpoint that does not read whole gives way to the one before it (with a note)."""
    run_dir, ckpt, payload = load_run_checkpoint(Path(path))
    config_path = run_dir / CONFIG_NAME
    config = load_config(config_path)
    if not isinstance(config, TrainerConfig):
        raise ValueError(f"{config_path} holds a {type(config).__name__}, not a TrainerConfig")
    pipeline = config.pipeline.setup(config.schedule.resolve(config.max_steps), config.seed, resolve_device(device))
    pipeline.load_state_dict(payload)
    return LoadedRun(run_dir, ckpt, int(payload["step"]), config, pipeline)
