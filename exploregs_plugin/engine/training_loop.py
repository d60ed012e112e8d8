"""The training loop, ``Trainer``: train steps, logging, evaluation, checkpoints, metrics. Its config
is ``exploregs_plugin.engine.trainer.TrainerConfig``, whose ``setup()`` builds it (this module does not
import the config back). What it calls between steps has modules of its own: ``stopping``
(signals), ``watches`` (when the collapse and non-finite watches are read), ``thread_follower``,
``run_folder`` and ``evaluation.ranks``."""

from __future__ import annotations

import os
import signal
import sys
import time
from dataclasses import replace
from functools import partial
from pathlib import Path
from typing import Any, Sequence

import torch

from exploregs_plugin.callbacks import TrainingCallback
from exploregs_plugin.io.config_files import load_config, save_config
from exploregs_plugin.runtime.device import resolve_device
from exploregs_plugin.runtime.distributed import init_world, params_checksum
from exploregs_plugin.evaluation.metrics import evaluate, write_metrics_json
from exploregs_plugin.io.checkpoint import (CheckpointError, checkpoint_path, load_checkpoint, load_run_checkpoint,
                                            save_checkpoint)
from exploregs_plugin.engine.pipeline import Pipeline, resolve_batch_size
from exploregs_plugin.evaluation.ranks import evaluate_on_ranks
from exploregs_plugin.rasterizer import backend_line
from exploregs_plugin.engine.run_folder import new_run_dir, run_folder_errors
from exploregs_plugin.engine.run_logger import RunLogger, host_values
from exploregs_plugin.engine.stopping import Stopped, StopOnSignals
from exploregs_plugin.engine.thread_follower import FollowIdleCpus, follows_idle_cpus
from exploregs_plugin.runtime.threads import apply_threads
from exploregs_plugin.engine.watches import RunWatches

CONFIG_NAME = "config.yml"
METRICS_NAME = "metrics.json"


class Trainer:
    """Owns the loop: train steps, logging, evaluation, checkpoints and metrics; everything else
    that acts between steps (viewer, diagnostics, probes) is a :class:`TrainingCallback`."""

    def __init__(self, config: Any, run_dir: Path | None = None, checkpoint: Path | None = None,
                 callbacks: Sequence[TrainingCallback] = (), payload: dict[str, Any] | None = None) -> None:
        """``config``: a :class:`exploregs_plugin.engine.trainer.TrainerConfig` (typed loosely: the config
        module builds the trainer, so the trainer does not import it back); ``payload``: the
        checkpoint's content when the caller has read it already."""
        self.config = config
        self.callbacks: list[TrainingCallback] = list(callbacks) + config.callbacks()
        if config.flush_denormal:
            torch.set_flush_denormal(True)
        if config.num_threads:
            apply_threads(config.num_threads)
        self.world, self.device = init_world(resolve_device(config.device), config.machine.timeout_minutes)
        if not self.world.is_main:  # rank 0 alone logs, serves the viewer and runs the diagnostics
            self.callbacks = []
            config = replace(config, quiet=True, tensorboard=False)
        # The batch is written into the run's config.yml, so a resume at another world size
        # keeps the same global batch (and so the same run).
        batch = resolve_batch_size(config.pipeline.batch_size, self.world.size)
        config = self.config = replace(config, pipeline=replace(config.pipeline, batch_size=batch))
        self.schedule = config.schedule.resolve(config.max_steps, batch)
        self.pipeline: Pipeline = config.pipeline.setup(self.schedule, config.seed, self.device, self.world)
        if self.world.is_main:  # after the data were read and checked: a data error is the first line
            print(backend_line(self.pipeline.model.config.raster, self.device), flush=True)
        # one run folder for all ranks: rank 0's (it claims a new timestamped folder unless one is named)
        named = run_dir or config.run_dir
        if named is None and self.world.is_main:
            named = new_run_dir(config.output_dir, self.pipeline.datamanager.scene_name, config.method_name)
        self.run_dir = Path(self.world.broadcast_object(str(named or "")))
        self.start_step = 0
        self.train_seconds = 0.0
        self.history: list[dict[str, Any]] = []
        # run-long sum of every strategy operation's count (one the strategy left on the device
        # stays a tensor there until it is read: _op_totals)
        self.op_totals: dict[str, Any] = {}
        self.last_checkpoint: Path | None = None
        self._checkpointed_at = 0.0  # train_seconds at the last checkpoint
        self._wall_before = 0.0  # wall-clock seconds of the run before this call to train() (a resume)
        self._wall_started: float | None = None
        self.watches = RunWatches(self.pipeline, self.schedule, config.collapse_watch, config.log_every,
                                  config.checkpoint_every, lambda: self.last_checkpoint)
        self.threads_used: set[int] = set()  # torch thread counts this run trained with (metrics.json)
        self.logger: RunLogger | None = None
        self._stop: StopOnSignals | None = None
        if checkpoint is not None:
            self._restore(checkpoint, payload)
        elif self.world.is_main:
            with run_folder_errors(self.run_dir):
                self.run_dir.mkdir(parents=True, exist_ok=True)
                save_config(config, self.run_dir / CONFIG_NAME)

    @property
    def stop_requested(self) -> bool:
        """Whether Ctrl-C asked the loop to stop at the next step boundary."""
        return self._stop is not None and self._stop.requested

    @classmethod
    def from_run(cls, path: Path, max_steps: int | None = None, quiet: bool | None = None,
                 callbacks: Sequence[TrainingCallback] = (), device: str | None = None,
                 num_devices: int | None = None) -> "Trainer":
        """Resume a run folder (or a checkpoint inside one) from its saved config; ``device``
        overrides the run's (a GPU run resumes on a CPU-only machine with device="cpu"), and
        ``num_devices`` its ranks per machine (the global batch stays the run's). A run folder
        resumes from its newest checkpoint that reads whole (a note names one that does not)."""
        # the ranks all read the same files: rank 0 alone notes a checkpoint it skipped
        note = partial(print, file=sys.stderr) if os.environ.get("RANK", "0") == "0" else None
        run_dir, ckpt, payload = load_run_checkpoint(Path(path), note)
        config = load_config(run_dir / CONFIG_NAME)
        if device is not None:
            config = replace(config, device=device)
        if num_devices is not None:
            config = replace(config, machine=replace(config.machine, num_devices=num_devices))
        if max_steps is not None:
            config = replace(config, max_steps=max_steps)
        if quiet is not None:
            config = replace(config, quiet=quiet)
        return cls(config, run_dir=run_dir, checkpoint=ckpt, callbacks=callbacks, payload=payload)

    # ----------------------------------------------------------------------------- loop
    def train(self) -> dict[str, Any]:
        """Run from ``start_step`` to ``max_steps``; returns the final metrics."""
        self._wall_started = time.perf_counter()
        try:
            with run_folder_errors(self.run_dir):
                return self._train()
        finally:
            self._wall_before, self._wall_started = self.wall_seconds, None

    @property
    def wall_seconds(self) -> float:
        """Wall-clock seconds of the run so far, evaluations, checkpoints and callbacks included
        (``train_seconds`` counts the training steps alone); a resumed run adds its earlier ones."""
        running = 0.0 if self._wall_started is None else time.perf_counter() - self._wall_started
        return self._wall_before + running

    def _train(self) -> dict[str, Any]:
        eval_steps = self._eval_steps()
        follow = follows_idle_cpus(self.config.num_threads, self.device, self.world.is_distributed)
        threads = FollowIdleCpus(self.threads_used) if follow else None
        self.threads_used.add(torch.get_num_threads())
        try:
            with RunLogger(self.run_dir, self.schedule.max_steps, self.start_step, self.config.log_every,
                           self.config.tensorboard, self.config.quiet) as logger, StopOnSignals() as stop:
                self.logger, self._stop = logger, stop
                for callback in self.callbacks:
                    callback.on_train_start(self)
                for step in range(self.start_step, self.schedule.max_steps):
                    self._before_step(step, stop, threads)
                    start = time.perf_counter()
                    stats = self._train_step(step)
                    stats["step_seconds"] = time.perf_counter() - start
                    self._after_step(step, stats, eval_steps)
                if self.schedule.max_steps not in eval_steps or not self.history:
                    self.run_eval(self.schedule.max_steps)
                self.save_checkpoint(self.schedule.max_steps)
                for callback in self.callbacks:
                    callback.on_train_end(self)
        finally:
            self.logger, self._stop = None, None
            if threads is not None:
                threads.restore()
            for callback in self.callbacks:
                callback.close()
        return self.write_metrics()

    def _before_step(self, step: int, stop: StopOnSignals, threads: FollowIdleCpus | None) -> None:
        """Callbacks, then the ranks' one agreement on a stop request or a due wall-clock
        checkpoint (so that they stop and checkpoint at the same step), then the thread count."""
        for callback in self.callbacks:
            callback.before_step(self, step)
        stop_now, minutes_due = self.world.any_of(stop.requested, self._minutes_due())
        if stop_now:
            self.save_checkpoint(step)
            raise Stopped(stop.signum or signal.SIGTERM, step, self.last_checkpoint)
        if minutes_due and step > self.start_step:
            self.save_checkpoint(step)
        if threads is not None:
            threads.check()
        note = self.pipeline.final_cut_note(step)
        if note:  # the cut after this step takes minutes on a large capture: say so before it
            self.logger.note(note)

    def _after_step(self, step: int, stats: dict[str, Any], eval_steps: set[int]) -> None:
        """Totals, the collapse watch, logging, callbacks, then evaluation and the periodic
        checkpoint due after ``step``."""
        self.train_seconds += stats["step_seconds"]
        for op, n in stats["counts"].items():  # a count may be a tensor on the device: read when saved
            self.op_totals[op] = self.op_totals.get(op, 0) + n
        if self.watches.reads_at(step, eval_steps):  # the wait for the device is training time
            start = time.perf_counter()
            self.watches.check(step, stats, read=True)
            self.train_seconds += time.perf_counter() - start
        else:
            self.watches.check(step, stats, read=False)
        self.logger.log_step(step, stats, self.pipeline.model.num_gaussians, self.pipeline.optim.lrs())
        for note in stats.get("notes", ()):  # e.g. the count a rule chose, and why
            self.logger.note(note)
        for callback in self.callbacks:
            callback.after_step(self, step + 1, stats)
        if step + 1 in eval_steps:
            self.run_eval(step + 1)
        if step + 1 < self.schedule.max_steps and (step + 1) % self.config.checkpoint_every == 0:
            self.save_checkpoint(step + 1)

    def _train_step(self, step: int) -> dict[str, Any]:
        try:
            return self.pipeline.train_step(step)
        except Exception as err:
            self.watches.after_failed_step(err)
            raise

    def _minutes_due(self) -> bool:
        """Whether checkpoint_minutes of training have passed since the last checkpoint."""
        minutes = self.config.checkpoint_minutes
        return minutes > 0 and self.train_seconds - self._checkpointed_at >= 60.0 * minutes

    def _eval_steps(self) -> set[int]:
        total, count = self.schedule.max_steps, max(1, self.config.eval_count)
        return {max(1, round(total * (i + 1) / count)) for i in range(count)}

    # ----------------------------------------------------------------------------- eval
    def run_eval(self, step: int) -> dict[str, Any]:
        """Evaluate on the test views and record a point of the PSNR-against-time curve. In a
        data-parallel run each rank scores every world-size-th view and rank 0 gathers the parts."""
        self.watches.read()
        final = step >= self.schedule.max_steps
        save_dir = self.run_dir / "renders" if (final and self.config.save_eval_images) else None
        metrics, panels = evaluate_on_ranks(self.pipeline, self.world, save_dir)
        self.history.append({"step": step, "train_seconds": self.train_seconds, "psnr": metrics["psnr"],
                             "ssim": metrics["ssim"], "num_gaussians": metrics["num_gaussians"],
                             **({"region_psnr": metrics["region_psnr"]} if "region_psnr" in metrics else {})})
        if self.logger is not None:
            self.logger.log_eval(step, metrics, panels)
            for name, value in self.pipeline.exploration_summary().items():
                self.logger.scalar(f"strategy/{name}", value, step)
        self.last_metrics = metrics
        return metrics

    def write_metrics(self) -> dict[str, Any]:
        metrics = dict(self.last_metrics)
        if self.world.is_distributed or self.pipeline.batch_size > 1:
            metrics.update({"batch_size": self.pipeline.batch_size, "world_size": self.world.size,
                            "images_seen": self.schedule.max_steps * self.pipeline.batch_size})
        metrics.update({
            "method": self.config.method_name,
            "scene": self.pipeline.datamanager.scene_name,
            "steps": self.schedule.max_steps,
            "seed": self.config.seed,
            "train_seconds": self.train_seconds,
            "wall_seconds": self.wall_seconds,
            "seconds_per_step": self.train_seconds / max(self.schedule.max_steps, 1),
            "threads": sorted(self.threads_used),
            "history": self.history,
            "strategy_counts": dict(sorted(self._op_totals().items())),
            "exploration": self.pipeline.exploration_summary(),
        })
        decision = self.pipeline.strategy.count_decision(self.pipeline.strategy_state)
        if decision:
            metrics["count_decision"] = decision
        cut_lines = self.pipeline.strategy.cut_lines(self.pipeline.strategy_state)
        if cut_lines:
            metrics["cut_lines"] = cut_lines
        if self.world.is_main:
            write_metrics_json(self.run_dir / METRICS_NAME, metrics)
        return metrics

    # ----------------------------------------------------------------------------- checkpoints
    def save_checkpoint(self, step: int) -> Path:
        """Rank 0 writes the checkpoint (atomically); first the ranks compare a checksum of their
        parameters, so that a checkpoint never holds one of several diverged models, and the
        watches are read, so that it never holds a non-finite or collapsed one."""
        self.watches.read()
        self.world.check_same(f"parameters at step {step}", torch.cat([
            params_checksum([p for _, p in self.pipeline.trained_tensors()]).to(self.device),
            torch.tensor([float(self.pipeline.model.num_gaussians)], dtype=torch.float64, device=self.device)]))
        if self.world.is_main:
            payload = {"version": 1, "step": step, "train_seconds": self.train_seconds,
                       "wall_seconds": self.wall_seconds, "history": self.history, "op_totals": self._op_totals(),
                       **self.pipeline.state_dict()}
            try:
                self.last_checkpoint = save_checkpoint(self.run_dir, step, payload, self.config.keep_checkpoints)
            except CheckpointError as err:  # a full disk: the run stops, the older checkpoint is whole
                raise CheckpointError(f"{err}; training stopped, {self.watches.last_good()}") from err
        else:  # rank 0 wrote it
            self.last_checkpoint = checkpoint_path(self.run_dir, step)
        self._checkpointed_at = self.train_seconds
        return self.last_checkpoint

    def _op_totals(self) -> dict[str, int]:
        """The run's operation counts as numbers (one read of the device)."""
        return {op: int(n) for op, n in host_values(self.op_totals).items()}

    def _restore(self, path: Path, payload: dict[str, Any] | None = None) -> None:
        payload = load_checkpoint(path) if payload is None else payload
        self.pipeline.load_state_dict(payload)
        if not self.pipeline.generator_restored:
            print(f"note: {path} was saved on another device type; its random stream continues reseeded "
                  f"(deterministic, not bit-identical to an uninterrupted run)", file=sys.stderr)
        self.start_step = int(payload["step"])
        self.train_seconds = float(payload.get("train_seconds", 0.0))
        self._wall_before = float(payload.get("wall_seconds", self.train_seconds))
        self.history = list(payload.get("history", []))
        self.op_totals = dict(payload.get("op_totals", {}))
        self.last_checkpoint = Path(path)
        if self.start_step >= self.schedule.max_steps:
            self.last_metrics = evaluate(self.pipeline.model, self.pipeline.datamanager)
        # a resumed checkpoint from another device or world: all ranks start from the same bits
        self.world.check_same("parameters after loading the checkpoint",
                              params_checksum([p for _, p in self.pipeline.trained_tensors()]))
