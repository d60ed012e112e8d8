"""A training run's config, ``TrainerConfig``: every eg-train flag, and the class a run folder's
``config.yml`` records. ``setup()`` builds the loop, :class:`exploregs_plugin.engine.training_loop.Trainer`,
which is importable from here too, with the run folder's file names."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Annotated, Any, Sequence

import tyro

from exploregs_plugin.callbacks import TrainingCallback
from exploregs_plugin.runtime.distributed import MachineConfig
from exploregs_plugin.engine.pipeline import PipelineConfig
from exploregs_plugin.engine.run_folder import RunFolderError  # noqa: F401 (importable here, as before)
from exploregs_plugin.schedule import ScheduleConfig
from exploregs_plugin.engine.stopping import Stopped  # noqa: F401 (importable here, as before)
from exploregs_plugin.engine.training_loop import CONFIG_NAME, METRICS_NAME, Trainer  # noqa: F401 (importable here)
from exploregs_plugin.viewer.callback import ViewerCallback
from exploregs_plugin.viewer.config import ViewerConfig


@dataclass
class TrainerConfig:
    """A complete training run. Every field can be set on the command line."""

    method_name: str = "exploregs-default"
    """Name of the method this config came from (recorded in the run folder)."""
    data: tyro.conf.Suppress[str | None] = None
    """Shortcut for pipeline.datamanager.data in Python (TrainerConfig(data=...)); not a flag of
    its own: --data is that field's flag."""
    data_factor: tyro.conf.Suppress[int | None] = None
    """Shortcut for pipeline.datamanager.data_factor (--data-factor is that field's flag)."""
    max_steps: int = 1500
    """Number of training steps (the schedule scales with it; see docs/training.md)."""
    seed: int = 0
    """Seed of every random choice (camera order, initialisation, strategies): same seed, same
    result on one machine and device."""
    device: str = "auto"
    """Where parameters, optimizer and strategy state live and rendering runs: auto (CUDA when
    available, else CPU), cpu, cuda or cuda:N."""
    schedule: ScheduleConfig = field(default_factory=ScheduleConfig)
    """Fractions of the run at which the 3DGS events happen."""
    machine: MachineConfig = field(default_factory=MachineConfig)
    """Data-parallel training over several processes and machines (--machine.*; docs/scale.md)."""
    pipeline: Annotated[PipelineConfig, tyro.conf.arg(name="")] = field(default_factory=PipelineConfig)
    """Data, model, optimizer, strategy and loss (set as --datamanager.*, --model.*, --strategy.*, ...)."""
    output_dir: Path = Path("outputs")
    """Runs go to OUTPUT_DIR/<scene>/<method>/<timestamp>/ (<timestamp>-2, ... for runs started in
    the same second)."""
    run_dir: Path | None = None
    """Use exactly this run folder instead of the timestamped one."""
    resume: Path | None = None
    """Continue the run in this folder from its latest checkpoint (its config.yml is used)."""
    eval_count: int = 5
    """Evaluate on the test views this many times, evenly spread (the last at the end)."""
    checkpoint_every: int = 500
    """Write a checkpoint every this many steps (and on Ctrl-C or SIGTERM, and at the end)."""
    checkpoint_minutes: float = 5.0
    """Also write one when this many minutes of training have passed since the last (0 = off),
    so a kill -9 or a power cut loses at most that much."""
    keep_checkpoints: int = 3
    """Keep only the newest this many checkpoints."""
    log_every: int = 10
    """Write tensorboard scalars every this many steps."""
    tensorboard: bool = True
    """Write tensorboard event files into the run folder."""
    save_eval_images: bool = True
    """At the end, save render | ground truth | error PNGs of every test view into RUN/renders/."""
    flush_denormal: bool = True
    """Flush denormal floats to zero (tiny alphas and gradients otherwise slow the CPU)."""
    num_threads: int | None = None
    """Every CPU thread of the run: torch's intra-op threads and the compositor's workers (unset:
    OMP_NUM_THREADS, else one per CPU this process may use that other processes leave idle,
    followed during the run; see docs/training.md, "Threads"). Parallel runs on one machine
    should split the cores."""
    quiet: bool = False
    """No progress bar or console lines."""
    collapse_watch: bool = True
    """Stop a run whose training PSNR or loss collapses (docs/training.md). Off: for strategies whose
    deliberate setbacks it does not know (a small prune of large opaque Gaussians can drop the
    training PSNR by 12 dB), at the cost of training on after a real collapse."""
    viewer: bool = False
    """Serve a live viewer in the browser while training (URL printed; see docs/viewer.md)."""
    viewer_config: ViewerConfig = field(default_factory=ViewerConfig)
    """Live viewer settings: port, render resolutions, CPU share, output (--viewer-config.*)."""

    def __post_init__(self) -> None:
        if self.checkpoint_every < 1:  # the periodic checkpoint is due when step % checkpoint_every == 0
            raise ValueError(f"--checkpoint-every must be >= 1, got {self.checkpoint_every}")
        # The top-level --data / --data-factor shortcuts are moved into the datamanager config
        # here, when the config is built (by tyro, a constructor or dataclasses.replace), so that
        # every consumer of the config sees one source of truth.
        updates: dict[str, Any] = {}
        if self.data is not None:
            updates["data"] = self.data
        if self.data_factor is not None:
            updates["data_factor"] = self.data_factor
        if updates:
            dm = replace(self.pipeline.datamanager, **updates)
            self.pipeline = replace(self.pipeline, datamanager=dm)
            self.data = self.data_factor = None

    def callbacks(self) -> list[TrainingCallback]:
        """The callbacks this config asks for, after those the caller passes: the live viewer
        with ``viewer``. A config variant adds its own (the branch-gradient logger of
        ``exploregs-grad-branches``), so a resumed run gets them back from its config.yml."""
        return [ViewerCallback(self.viewer_config)] if self.viewer else []

    def setup(self, callbacks: Sequence[TrainingCallback] = ()) -> "Trainer":
        if self.resume is not None:
            return Trainer.from_run(self.resume, max_steps=None, quiet=self.quiet, callbacks=callbacks)
        return Trainer(self, callbacks=callbacks)
