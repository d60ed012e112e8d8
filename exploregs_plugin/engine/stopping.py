"""Stopping a training run on a signal: Ctrl-C's SIGINT, SIGTERM from a scheduler, a container or
``kill``, and (in a rank of eg-train's launcher) the SIGHUP of a launcher that died. The trainer
stops at the next step boundary with a checkpoint and raises :class:`Stopped`."""

from __future__ import annotations

import signal
import threading
from pathlib import Path
from typing import Any

from exploregs_plugin.runtime.distributed import LAUNCHER_GONE, launched_by_eg_train

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


class Stopped(KeyboardInterrupt):
    """Training stopped on a signal (Ctrl-C's SIGINT, or SIGTERM from a scheduler, a container or
    ``kill``) at a step boundary, after writing a checkpoint. ``exit_code`` is 128 + signal."""

    def __init__(self, signum: int, step: int | None = None, checkpoint: Path | None = None,
                 where: str = "before training started") -> None:
        self.signum, self.step, self.checkpoint = signum, step, checkpoint
        name = signal.Signals(signum).name
        if signum == LAUNCHER_GONE:
            name += " (its launcher is gone)"
        if step is not None:  # ``step`` steps are done (the progress line's count); the checkpoint holds them
            where = f"after step {step}" if step else "before the first step"
            where += f", saved in {checkpoint}"
        super().__init__(f"stopped by {name} {where}")

    @property
    def exit_code(self) -> int:
        return 128 + self.signum


class StopOnSignals:
    """The first SIGINT or SIGTERM (or, in a rank of eg-train's launcher, SIGHUP) asks the loop to
    stop at the next step boundary (so the checkpoint holds a consistent state, never half an
    optimizer step); a second SIGINT or SIGTERM stops at once. Repeats of SIGHUP are one request:
    the kernel sends a launched rank one per thread of its dying launcher (see
    ``distributed.LAUNCHER_GONE``), and a rank that left at once would leave the others waiting in
    a collective; once one came, later ones are ignored to the end of the process (they may still
    arrive while the rank leaves its group). A SIGINT that is ignored when training starts stays
    ignored; SIGTERM is always taken, as the stop request of a scheduler or a container. Installed
    from the main thread only (Python delivers signals there)."""

    def __init__(self) -> None:
        self.signum: int | None = None
        self.launcher_gone = False
        self._previous: dict[int, Any] = {}

    @property
    def requested(self) -> bool:
        return self.signum is not None

    def _handler(self, signum: int, frame: Any) -> None:
        if self.signum is not None and signum != LAUNCHER_GONE:
            raise Stopped(signum, where="at once, without a checkpoint (a second signal)")
        self.signum = self.signum or signum
        self.launcher_gone |= signum == LAUNCHER_GONE

    def __enter__(self) -> "StopOnSignals":
        if threading.current_thread() is threading.main_thread():
            signals = STOP_SIGNALS + ((LAUNCHER_GONE,) if launched_by_eg_train() else ())
            if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
                # as a shell leaves it for a command that a script starts in the background
                # (bash -c 'eg-train ... &'), so that a Ctrl-C meant for the foreground does not
                # reach it; Python installs no handler then, and neither do we. (The ranks of
                # eg-train's launcher and of torchrun start with SIGINT at its default: the
                # launcher takes SIGINT itself before it starts them, and passes it on to stop them.)
                signals = tuple(s for s in signals if s != signal.SIGINT)
            self._previous = {s: signal.signal(s, self._handler) for s in signals}
        return self

    def __exit__(self, *exc: Any) -> None:
        for s, previous in self._previous.items():
            if s == LAUNCHER_GONE and self.launcher_gone:
                previous = signal.SIG_IGN
            signal.signal(s, signal.SIG_DFL if previous is None else previous)
