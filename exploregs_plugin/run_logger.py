"""Tensorboard scalars/images and the console progress display for a training run."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn


class RunLogger:
    """Writes tensorboard events into the run folder and drives a rich progress bar.

    Operation counts from the strategy are summed between two log steps, so
    ``strategy/<op>`` is the number of Gaussians that operation touched in that window.
    """

    def __init__(self, run_dir: Path, total_steps: int, start_step: int, log_every: int,
                 tensorboard: bool = True, quiet: bool = False) -> None:
        self.log_every = max(1, log_every)
        self.writer = None
        if tensorboard:
            from torch.utils.tensorboard import SummaryWriter

            self.writer = SummaryWriter(log_dir=str(run_dir))
        self.console = Console(stderr=True)
        self.quiet = quiet
        self.counts: dict[str, int] = {}
        self.window_start = time.perf_counter()
        self.window_steps = 0
        self.total_steps = total_steps
        # No remaining-time column: steps slow down as the Gaussians multiply (9 to 2.6 it/s on the
        # README's job), so an estimate from the rate so far is 2-3x too low for most of a run.
        # The bar shows the elapsed time and the recent rate (it/s in the stats) instead.
        self.progress = Progress(
            TextColumn("[bold]train"), BarColumn(), TextColumn("{task.completed}/{task.total}"),
            TextColumn("{task.fields[stats]}"), TextColumn("elapsed"), TimeElapsedColumn(),
            console=self.console, disable=quiet or not self.console.is_terminal,
        )
        self.task = self.progress.add_task("train", total=total_steps, completed=start_step, stats="")

    def __enter__(self) -> "RunLogger":
        self.progress.start()
        return self

    def __exit__(self, *exc: Any) -> None:
        self.progress.stop()
        if self.writer is not None:
            self.writer.flush()
            self.writer.close()

    def scalar(self, tag: str, value: float, step: int) -> None:
        if self.writer is not None:
            self.writer.add_scalar(tag, value, step)

    def log_step(self, step: int, stats: dict[str, Any], num_gaussians: int, lrs: dict[str, float]) -> None:
        for op, n in stats["counts"].items():
            self.counts[op] = self.counts.get(op, 0) + int(n)
        self.window_steps += 1
        self.progress.update(self.task, completed=step + 1)
        if (step + 1) % self.log_every and step + 1 != self.total_steps:
            return
        seconds_per_step = (time.perf_counter() - self.window_start) / max(self.window_steps, 1)
        self.scalar("train/loss", stats["loss"], step)
        for name, value in stats["terms"].items():
            self.scalar(f"train/{name}", value, step)
        self.scalar("train/psnr", stats["psnr"], step)
        self.scalar("gaussians/count", num_gaussians, step)
        self.scalar("perf/seconds_per_step", seconds_per_step, step)
        for name, lr in lrs.items():
            self.scalar(f"lr/{name}", lr, step)
        for op, n in self.counts.items():
            self.scalar(f"strategy/{op}", n, step)
        text = (f"{1.0 / max(seconds_per_step, 1e-9):5.1f} it/s  loss {stats['loss']:.4f}  "
                f"psnr {stats['psnr']:5.2f}  #G {num_gaussians}")
        self.progress.update(self.task, stats=text)
        # Without a terminal (CI, log files) the bar is off: print a line every 10 log windows.
        every = self.log_every * 10
        if self.progress.disable and not self.quiet and ((step + 1) % every == 0 or step + 1 == self.total_steps):
            self.console.print(f"step {step + 1}/{self.total_steps}  {text}")
        self.counts = {}
        self.window_start = time.perf_counter()
        self.window_steps = 0

    def log_eval(self, step: int, metrics: dict[str, Any], panels: list[tuple[str, torch.Tensor]]) -> None:
        self.scalar("test/psnr", metrics["psnr"], step)
        self.scalar("test/ssim", metrics["ssim"], step)
        for key in ("ms_ssim", "dssim"):  # D-SSIM = (1 - MS-SSIM) / 2 (the loss's train/dssim is 1 - SSIM)
            if np.isfinite(metrics.get(key, float("nan"))):
                self.scalar(f"test/{key}", metrics[key], step)
        for region, value in metrics.get("region_psnr", {}).items():
            if np.isfinite(value):
                self.scalar(f"test/psnr_{region}", value, step)
        if self.writer is not None:
            for name, panel in panels:
                self.writer.add_image(f"test/{name}", panel.clamp(0, 1).numpy(), step, dataformats="HWC")
        if not self.quiet:
            self.console.print(f"eval @ {step}: PSNR {metrics['psnr']:.2f} dB  SSIM {metrics['ssim']:.4f}")
