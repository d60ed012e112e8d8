"""CPU threads of every command: passive OpenMP waiting, and a thread count from the CPUs this
process may use.

This module imports nothing heavy: ``exploregs_plugin/__init__.py`` calls
:func:`prefer_passive_waiting` before any module of the package imports torch, because the
OpenMP runtime reads its environment once, when torch loads it.
"""

from __future__ import annotations

import os

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


def default_threads() -> int:
    """OMP_NUM_THREADS when set (by the user, or by the launcher of a data-parallel job for the
    ranks that share the cores), else one thread per CPU this process may use."""
    value = os.environ.get(THREADS, "").strip()
    if value.isdigit() and int(value) >= 1:
        return int(value)
    return available_cpus()


def apply_threads(num_threads: int | None = None) -> int:
    """Set torch's intra-op thread count (which also bounds the compositor's workers) to
    ``num_threads``, or to :func:`default_threads` when it is None; returns the count."""
    import torch

    count = num_threads or default_threads()
    if torch.get_num_threads() != count:
        torch.set_num_threads(count)
    return count
