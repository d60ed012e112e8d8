"""Progress of eg-process's stages: a rich bar on a terminal, and plain lines in ``OUT/process.log``
(and on the console when it is not a terminal, as in ``eg-train ... > run.log``), so that a long
stage, mapping above all, is seen to move wherever its output goes.

A line is written when a stage starts and ends and, in between, every ``LINE_SECONDS`` from a
small thread, whether or not the count moved: the global mapper reports nothing until it is done,
and "still mapping, 3 min 10 s" is what a user watching a log needs to see.
"""

from __future__ import annotations

import threading
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Callable, Iterator

from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)

LOG_NAME = "process.log"
LINE_SECONDS = 15.0


def elapsed_text(seconds: float) -> str:
    """``42 s`` or ``3 min 10 s``."""
    seconds = int(round(seconds))
    return f"{seconds} s" if seconds < 60 else f"{seconds // 60} min {seconds % 60} s"


class StageLog:
    """Appends time-stamped lines to ``OUT/process.log`` and, off a terminal, prints them."""

    def __init__(self, out: Path, console: Console) -> None:
        self.path, self.console = out / LOG_NAME, console
        self._lock = threading.Lock()

    def line(self, text: str, show: bool = False) -> None:
        """``text`` into the log; on the console too when it is not a terminal (where the bars
        say it), or always with ``show`` (a choice or a note the user should read)."""
        stamped = f"{time.strftime('%Y-%m-%d %H:%M:%S')} {text}"
        with self._lock:
            with open(self.path, "a", encoding="utf-8") as f:
                f.write(stamped + "\n")
            if show or not self.console.is_terminal:
                self.console.print(text, highlight=False, soft_wrap=True, markup=False)


class _Counter:
    """The state a stage reports: done of total (None: unknown), and what it counts."""

    def __init__(self, description: str, total: int | None, unit: str) -> None:
        self.description, self.total, self.unit = description, total, unit
        self.done = 0
        self.start = time.perf_counter()

    def text(self) -> str:
        if self.total:
            counted = f"{self.done} of {self.total} {self.unit}"
        else:  # a stage that reports nothing until it is done (the global mapper)
            counted = f"{self.done} {self.unit}" if self.done else "running"
        return f"{self.description}: {counted}, {elapsed_text(time.perf_counter() - self.start)}"


@contextmanager
def stage_progress(console: Console, log: StageLog, description: str, total: int | None,
                   unit: str = "") -> Iterator[Callable[..., None]]:
    """Yields ``update(advance=1, completed=None)``: a rich bar on a terminal, and lines in the
    log at the start, every LINE_SECONDS and at the end."""
    counter = _Counter(description, total, unit or "done")
    stop = threading.Event()

    def tick() -> None:
        while not stop.wait(LINE_SECONDS):
            log.line(counter.text())

    log.line(f"{description}: started" + (f", {total} {counter.unit}" if total else ""))
    ticker = threading.Thread(target=tick, name=f"progress-{description}", daemon=True)
    ticker.start()
    columns = (TextColumn("{task.description:<10}"), BarColumn(), MofNCompleteColumn(),
               TimeElapsedColumn(), TextColumn("ETA"), TimeRemainingColumn())
    # off a terminal rich would print the bar only when it stops: the log lines say it instead
    with Progress(*columns, console=console, transient=False, disable=not console.is_terminal) as progress:
        task = progress.add_task(description, total=total)

        def update(advance: int = 1, completed: int | None = None) -> None:
            counter.done = completed if completed is not None else counter.done + advance
            progress.update(task, advance=advance, completed=completed)

        try:
            yield update
        finally:
            stop.set()
            ticker.join()
    log.line(counter.text() + " (done)")
