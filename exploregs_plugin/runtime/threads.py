"""CPU threads of every command: passive OpenMP waiting, and a thread count from the CPUs this
process may use that other processes leave idle.

This module imports nothing heavy: ``exploregs_plugin/__init__.py`` calls
:func:`prefer_passive_waiting` before any module of the package imports torch, because the
OpenMP runtime reads its environment once, when torch loads it.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

WAIT_POLICY = "OMP_WAIT_POLICY"
THREADS = "OMP_NUM_THREADS"


def prefer_passive_waiting() -> None:
    """OpenMP threads sleep while they wait, instead of spinning (a value the user set is kept).

    Why: at the end of every parallel region OpenMP's default lets the finished threads spin for a
    while. On a machine shared with another busy process one thread of the region waits for a core
    the other process holds, and the spinning ones burn the cores it could have had: a 300-step
    run took 334-407 s at the default threads against 35 s at one thread (issue 31); passive
    waiting removes that collapse (docs/training.md, "Threads").
    """
    os.environ.setdefault(WAIT_POLICY, "PASSIVE")


def available_cpus() -> int:
    """The CPUs this process may run on (its affinity: taskset, a container's cpuset), which can
    be fewer than the machine's cores."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):  # no sched_getaffinity (macOS, Windows)
        return os.cpu_count() or 1


def threads_from_environment() -> int | None:
    """OMP_NUM_THREADS when set to a count (by the user, or by the launcher of a data-parallel
    job for the ranks that share the cores), else None."""
    value = os.environ.get(THREADS, "").strip()
    return int(value) if value.isdigit() and int(value) >= 1 else None


class IdleCpus:
    """How many of this process's CPUs other processes left idle since the last :meth:`sample`.

    Why: the compositor's worker threads and torch's parallel ops assume each thread owns a core.
    With another busy process on a 2-core machine, two threads collapse (40 steps of
    ``exploregs-seedsplit`` on ``builtin:default``: 386 s at 2 threads against 9.4 s at one;
    docs/training.md, "Threads"), because every barrier and GIL hand-over waits for a thread that
    the scheduler gave no core. Reads /proc/stat (the busy time of the CPUs in this process's
    affinity) and /proc/self/stat (this process's own CPU time, which is not "other"); None where
    there is no /proc (not Linux).
    """

    def __init__(self, proc: Path = Path("/proc")) -> None:
        self.proc = proc
        self.cpus = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else []
        self._last = self._read()

    def _read(self) -> tuple[int, int, int] | None:
        """(busy ticks, all ticks) summed over this process's CPUs, and this process's own ticks."""
        try:
            wanted = {f"cpu{c}" for c in self.cpus}
            busy = total = 0
            for line in (self.proc / "stat").read_text().splitlines():
                fields = line.split()
                if fields and fields[0] in wanted:
                    user, nice, system, idle, iowait, irq, softirq, steal = (int(v) for v in fields[1:9])
                    busy += user + nice + system + irq + softirq + steal
                    total += user + nice + system + idle + iowait + irq + softirq + steal
            own = (self.proc / "self" / "stat").read_text().rsplit(")", 1)[1].split()
            return busy, total, int(own[11]) + int(own[12])  # utime + stime
        except (OSError, ValueError, IndexError):
            return None

    def sample(self) -> float | None:
        """CPUs (a fraction) of this process's set that other processes left idle since the last
        call; None when unknown (no /proc, or too little time passed)."""
        now = self._read()
        last, self._last = self._last, now
        if now is None or last is None or not self.cpus:
            return None
        busy, total, own = (a - b for a, b in zip(now, last))
        per_cpu = total / len(self.cpus)
        if per_cpu < 5:  # under about 50 ms of ticks: too short to say
            return None
        others = max(0.0, (busy - own) / per_cpu)
        return max(0.0, len(self.cpus) - others)


IDLE_SHARE_FOR_A_THREAD = 0.75
"""How much of a CPU other processes must leave idle for it to get a thread of its own."""


def threads_for(idle: float | None, cpus: int) -> int:
    """One thread per CPU that other processes leave idle, counting a partly idle CPU only when at
    least IDLE_SHARE_FOR_A_THREAD of it is free (at least one thread); every CPU when unknown.

    Why not rounding to the nearest (1.5 idle CPUs -> 2 threads): a parallel region split into
    equal parts (torch's element-wise ops, the kernels' ``schedule(static)`` loops) ends when its
    slowest thread does. With n threads, one of which gets a share s < 1 of its core, the region
    takes W / (n s) instead of W / n: two threads beat one only when s > 1/2, and every region's
    end also waits until that thread is scheduled again. At s = 1/2 the second thread gains
    nothing and pays those waits, so the default could lose to one thread beside a process that
    takes half a CPU; a thread per CPU that is 3/4 free keeps the default at one thread until a
    second thread can be clearly ahead. With k processes that keep a CPU busy each on C CPUs, n
    threads measure C - k C / (n + k) idle (the scheduler's fair shares), so from n = C the count
    falls to C - k and stays there (tests/test_framework_threads.py)."""
    if idle is None:
        return cpus
    return max(1, min(cpus, int(idle + 1.0 - IDLE_SHARE_FOR_A_THREAD)))


def default_threads(measure_seconds: float = 0.2) -> int:
    """OMP_NUM_THREADS when set, else one thread per CPU this process may use that other
    processes leave idle (measured over ``measure_seconds``)."""
    from_env = threads_from_environment()
    if from_env is not None:
        return from_env
    watch = IdleCpus()
    time.sleep(measure_seconds)
    return threads_for(watch.sample(), available_cpus())


def apply_threads(num_threads: int | None = None) -> int:
    """Set torch's intra-op thread count (which also bounds the compositor's workers) to
    ``num_threads``, or to :func:`default_threads` when it is None; returns the count."""
    import torch

    count = num_threads or default_threads()
    if torch.get_num_threads() != count:
        torch.set_num_threads(count)
    return count
