"""A training run's thread count follows the CPUs other processes leave idle (docs/training.md,
"Threads"): checked between steps, set through torch (which bounds the compositor's workers)."""

from __future__ import annotations

import time

import torch

from exploregs_plugin.runtime.threads import IdleCpus, available_cpus, threads_for, threads_from_environment

THREADS_CHECK_SECONDS = 5.0  # how often a run without --num-threads follows the CPUs left idle
# ... and the first time, after this much training: the count the run starts with was measured when
# the command started, before the data loaded, and a competitor may have come or gone since
FIRST_THREADS_CHECK_SECONDS = 1.0


def follows_idle_cpus(num_threads: int | None, device: torch.device, distributed: bool) -> bool:
    """A CPU run whose thread count nobody set (no --num-threads, no OMP_NUM_THREADS) follows the
    CPUs other processes leave idle; the ranks of a data-parallel job keep theirs (they split the
    cores between them)."""
    return num_threads is None and threads_from_environment() is None and device.type == "cpu" and not distributed


class FollowIdleCpus:
    """Every THREADS_CHECK_SECONDS, between steps, set torch's thread count (which bounds the
    compositor's workers) to the CPUs other processes left idle: a process that starts competing
    for the cores mid-run takes the run down to one thread instead of stalling it (see
    :class:`exploregs_plugin.runtime.threads.IdleCpus`), and one that ends gives the cores back. The
    count changes the speed, not the result (docs/training.md, "Threads")."""

    def __init__(self, used: set[int]) -> None:
        self.used = used  # every count set is added here
        self.watch = IdleCpus()
        self.cpus = available_cpus()
        self.before = torch.get_num_threads()
        self.checked = time.monotonic() - THREADS_CHECK_SECONDS + FIRST_THREADS_CHECK_SECONDS

    def check(self) -> None:
        if time.monotonic() - self.checked < THREADS_CHECK_SECONDS:
            return
        self.checked = time.monotonic()
        wanted = threads_for(self.watch.sample(), self.cpus)
        if wanted != torch.get_num_threads():
            torch.set_num_threads(wanted)
            self.used.add(wanted)

    def restore(self) -> None:
        if torch.get_num_threads() != self.before:
            torch.set_num_threads(self.before)
