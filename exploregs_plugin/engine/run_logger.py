"""Tensorboard scalars/images and the console progress display for a training run."""

from __future__ import annotations

import sys
import threading
import time
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import torch
from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

WRITER_THREAD = "_AsyncWriterThread"  # tensorboard's thread that writes the event file


class RunLogger:
    """Writes tensorboard events into the run folder and drives a rich progress bar.

    Operation counts from the strategy are summed between two log steps, so
    ``strategy/<op>`` is the number of Gaussians that operation touched in that window.

    A tensorboard writer that cannot write (a full disk) is closed with one line and the run goes
    on without it: the events are a log, the checkpoints and metrics are what must survive.
    """

    def __init__(self, run_dir: Path, total_steps: int, start_step: int, log_every: int,
                 tensorboard: bool = True, quiet: bool = False) -> None:
        self.log_every = max(1, log_every)
        self.writer = None
        if tensorboard:
            from torch.utils.tensorboard import SummaryWriter

            try:
                self.writer = SummaryWriter(log_dir=str(run_dir))
            except OSError as err:
                _events_stopped(err)
        self.console = Console(stderr=True)
        self.quiet = quiet
        self.counts: dict[str, int] = {}
        self.window_start = time.perf_counter()
        self.window_steps = 0
        self.total_steps = total_steps
        self.started = time.perf_counter()
        # The remaining time is estimated from the recent rate (the last log window, evaluations
        # and checkpoints included), not the rate so far: steps slow down as the Gaussians multiply
        # (9 to 2.6 it/s on the README's job), so the estimate grows while the Gaussians do, until
        # densification stops at half the run (docs/training.md says so).
        self.progress = Progress(
            TextColumn("[bold]train"), BarColumn(), TextColumn("{task.completed}/{task.total}"),
            TextColumn("{task.fields[stats]}"), TextColumn("elapsed"), TimeElapsedColumn(),
            TextColumn("{task.fields[eta]}"),
            console=self.console, disable=quiet or not self.console.is_terminal,
        )
        self.task = self.progress.add_task("train", total=total_steps, completed=start_step, stats="", eta="")

    def __enter__(self) -> "RunLogger":
        self._excepthook = threading.excepthook
        threading.excepthook = self._writer_thread_failed
        self.progress.start()
        return self

    def __exit__(self, *exc: Any) -> None:
        self.progress.stop()
        self._guard(lambda w: (w.flush(), w.close()))
        threading.excepthook = self._excepthook

    def _writer_thread_failed(self, args: Any) -> None:
        """tensorboard's writer thread dies on a full disk and prints a traceback; its error is
        raised again at the next write, where :meth:`_guard` reports it in one line."""
        if type(args.thread).__name__ == WRITER_THREAD and isinstance(args.exc_value, OSError):
            return
        self._excepthook(args)

    def _guard(self, write: Any) -> None:
        """``write(writer)``; an OSError (the disk is full, the folder went away) stops the
        tensorboard events with one line instead of stopping the run."""
        if self.writer is None:
            return
        try:
            write(self.writer)
        except OSError as err:
            writer, self.writer = self.writer, None
            _events_stopped(err)
            try:
                writer.close()
            except OSError:
                pass

    def scalar(self, tag: str, value: float, step: int) -> None:
        self._guard(lambda w: w.add_scalar(tag, value, step))

    def log_step(self, step: int, stats: dict[str, Any], num_gaussians: int, lrs: dict[str, float]) -> None:
        """Sum the step's counts into the window; at a log step, read the step's values and the
        window's counts from the device (one read) and write them. ``stats``' loss, psnr, terms
        and counts may be tensors on the device (the pipeline's are) or numbers."""
        for op, n in stats["counts"].items():
            self.counts[op] = self.counts.get(op, 0) + n
        self.window_steps += 1
        self.progress.update(self.task, completed=step + 1)
        if (step + 1) % self.log_every and step + 1 != self.total_steps:
            return
        seconds_per_step = (time.perf_counter() - self.window_start) / max(self.window_steps, 1)
        read = host_values({"loss": stats["loss"], "psnr": stats["psnr"],
                            **{f"train/{name}": value for name, value in stats["terms"].items()},
                            **{f"strategy/{op}": n for op, n in self.counts.items()}})
        stats = {**stats, "loss": read.pop("loss"), "psnr": read.pop("psnr")}
        self.counts = {op: int(read.pop(f"strategy/{op}")) for op in self.counts}
        self.scalar("train/loss", stats["loss"], step)
        for tag, value in read.items():  # the terms
            self.scalar(tag, value, step)
        self.scalar("train/psnr", stats["psnr"], step)
        self.scalar("gaussians/count", num_gaussians, step)
        self.scalar("perf/seconds_per_step", seconds_per_step, step)
        for name, lr in lrs.items():
            self.scalar(f"lr/{name}", lr, step)
        for op, n in self.counts.items():
            self.scalar(f"strategy/{op}", n, step)
        text = (f"{1.0 / max(seconds_per_step, 1e-9):5.1f} it/s  loss {stats['loss']:.4f}  "
                f"psnr {stats['psnr']:5.2f}  #G {num_gaussians}")
        eta = f"ETA {clock((self.total_steps - step - 1) * seconds_per_step)}"
        self.progress.update(self.task, stats=text, eta=eta)
        # Without a terminal (CI, log files) the bar is off: print a line every 10 log windows.
        every = self.log_every * 10
        if self.progress.disable and not self.quiet and ((step + 1) % every == 0 or step + 1 == self.total_steps):
            elapsed = clock(time.perf_counter() - self.started)
            self.console.print(f"step {step + 1}/{self.total_steps}  {text}  elapsed {elapsed}  {eta}", soft_wrap=True)
        self.counts = {}
        self.window_start = time.perf_counter()
        self.window_steps = 0

    def note(self, text: str) -> None:
        """One line of what the run decided (above the progress bar; not with quiet)."""
        if not self.quiet:
            self.console.print(text, soft_wrap=True)

    def log_eval(self, step: int, metrics: dict[str, Any], panels: list[tuple[str, torch.Tensor]]) -> None:
        self.scalar("test/psnr", metrics["psnr"], step)
        self.scalar("test/ssim", metrics["ssim"], step)
        # D-SSIM = (1 - MS-SSIM) / 2 (the loss's train/dssim is 1 - SSIM); LPIPS is None without weights
        for key in ("ms_ssim", "dssim", "lpips"):
            if metrics.get(key) is not None and np.isfinite(metrics[key]):
                self.scalar(f"test/{key}", metrics[key], step)
        for region, value in metrics.get("region_psnr", {}).items():
            if np.isfinite(value):
                self.scalar(f"test/psnr_{region}", value, step)
        for name, panel in panels:
            self._guard(lambda w: w.add_image(f"test/{name}", panel.clamp(0, 1).numpy(), step, dataformats="HWC"))
        if not self.quiet:
            self.console.print(f"eval @ {step}: PSNR {metrics['psnr']:.2f} dB  SSIM {metrics['ssim']:.4f}")


def host_values(values: Mapping[str, Any]) -> dict[str, float]:
    """``values`` as Python floats: the tensors among them (0-dim, on one device) read together,
    one wait for the device instead of one per value; numbers are passed through."""
    tensors = {key: value for key, value in values.items() if isinstance(value, torch.Tensor)}
    read = dict(zip(tensors, torch.stack([t.detach().reshape(()).to(torch.float64) for t in tensors.values()]).tolist()
                    if tensors else []))
    return {key: read[key] if key in read else float(value) for key, value in values.items()}


def _events_stopped(err: OSError) -> None:
    print(f"warning: tensorboard events stopped, they cannot be written ({err.strerror or err}); "
          f"training goes on", file=sys.stderr)


def clock(seconds: float) -> str:
    """``H:MM:SS`` (or ``M:SS`` under an hour) for progress lines."""
    whole = max(0, int(round(seconds)))
    hours, rest = divmod(whole, 3600)
    return f"{hours}:{rest // 60:02d}:{rest % 60:02d}" if hours else f"{rest // 60}:{rest % 60:02d}"
