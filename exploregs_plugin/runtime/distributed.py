"""Data-parallel training with torch.distributed: one process per device, on one or more machines.

A run is a *world* of ranks. ``torchrun`` (or ``eg-train --machine.num-devices N``, which launches
through the same engine) starts one process per device and sets ``RANK``, ``WORLD_SIZE``,
``LOCAL_RANK`` and the rendezvous address in its environment; :func:`init_world` reads them and
joins the process group (NCCL on CUDA, gloo on the CPU). A process started without them is a
world of one, and every collective here is then a no-op, so single-process code pays nothing.

Why the ranks stay identical: every rank holds the whole Gaussian set and draws every random
number (camera order, seeds, splits, noise, relocation) from generators seeded alike; the
gradients are summed with one all-reduce, and every rank sees every view's densification
observations (gathered) before a strategy decides. :meth:`World.check_same` compares a
parameter checksum across ranks so that a drift stops the run instead of going unnoticed.
"""

from __future__ import annotations

import ctypes
import datetime
import gc
import os
import re
import signal
import sys
from dataclasses import dataclass
from typing import Any, Sequence

import torch
from torch import Tensor

RANK_ENV = ("RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT")
"""What torchrun puts in each worker's environment."""


class DistributedError(RuntimeError):
    """The ranks of a run cannot work together (a rank was lost, or the ranks disagree)."""


class DivergenceError(DistributedError):
    """The ranks hold different parameters: the run stops instead of training several models."""


class PeerLostError(DistributedError):
    """A collective failed because another rank stopped or died (its launcher names which)."""


LAUNCHER_PID = "EXPLOREGS_LAUNCHER_PID"
"""Set by ``eg-train --machine.num-devices N`` for its ranks: the pid of the launcher, which
reports a lost rank itself (so the ranks that lost it say nothing)."""
PR_SET_PDEATHSIG = 1  # linux/prctl.h
LAUNCHER_GONE = signal.SIGHUP
"""What a rank of eg-train's launcher gets when the launcher dies: SIGHUP (it hung up), not the
SIGTERM a user or scheduler sends, because the kernel sends the parent-death signal again for
every thread of the dying launcher that adopts the rank on the way out (prctl(2)): repeats of
this one are one request, while a second SIGTERM or Ctrl-C means "stop now"."""


def launched_by_eg_train(environ: dict[str, str] | None = None) -> bool:
    """Whether this rank was started by eg-train's own launcher (not by a torchrun command)."""
    return LAUNCHER_PID in (os.environ if environ is None else environ)


def stop_with_launcher() -> None:
    """Ask the kernel to send this rank :data:`LAUNCHER_GONE` when its launcher dies (even by
    kill -9), so no rank trains on as an orphan: the ranks agree to stop at the next step and
    checkpoint, as for SIGTERM. Linux only (prctl); elsewhere a no-op."""
    if not sys.platform.startswith("linux"):
        return
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        if libc.prctl(PR_SET_PDEATHSIG, int(LAUNCHER_GONE), 0, 0, 0) != 0:
            return
    except (OSError, AttributeError):
        return
    # the launcher may have died before the request was made: then no signal will ever come
    launcher = os.environ.get(LAUNCHER_PID)
    if launcher is not None and launcher.isdigit() and os.getppid() != int(launcher):
        os.kill(os.getpid(), LAUNCHER_GONE)


def launched_by_torchrun(environ: dict[str, str] | None = None) -> bool:
    """Whether this process is one rank of a torchrun launch (its environment names a world)."""
    env = os.environ if environ is None else environ
    return "RANK" in env and "WORLD_SIZE" in env


@dataclass
class MachineConfig:
    """How many processes train together (nerfstudio's --machine.* names). One process per
    device: ``eg-train --machine.num-devices N`` launches N ranks here through torch's elastic
    launcher (the engine of torchrun); under ``torchrun`` these fields are ignored."""

    num_devices: int = 1
    """Processes (ranks) on this machine: one per GPU, or CPU processes sharing the cores."""
    num_machines: int = 1
    """Machines taking part; start eg-train on each with its own --machine.machine-rank."""
    machine_rank: int = 0
    """This machine's rank among them (0 hosts the rendezvous)."""
    master_addr: str = "127.0.0.1"
    """Address of machine 0 (every machine must reach it)."""
    master_port: int = 0
    """Port of the rendezvous on machine 0. 0: a free port (one machine only)."""
    timeout_minutes: float = 10.0
    """How long a collective waits for a silent rank before the run fails."""

    def __post_init__(self) -> None:
        if self.num_devices < 1 or self.num_machines < 1:
            raise ValueError("--machine.num-devices and --machine.num-machines must be >= 1")
        if not 0 <= self.machine_rank < self.num_machines:
            raise ValueError(f"--machine.machine-rank must be in [0, {self.num_machines}), got {self.machine_rank}")
        if self.num_machines > 1 and self.master_port == 0:
            raise ValueError("several machines need a fixed --machine.master-port on machine 0")
        if self.timeout_minutes <= 0:
            raise ValueError("--machine.timeout-minutes must be positive")

    @property
    def world_size(self) -> int:
        return self.num_devices * self.num_machines


@dataclass(frozen=True)
class World:
    """This process's place among the ranks: ``rank`` of ``size``, ``local_rank`` on its machine."""

    rank: int = 0
    size: int = 1
    local_rank: int = 0
    device: str = "cpu"
    """Where this rank's collectives put their small tensors (its CUDA device under NCCL)."""

    @property
    def is_main(self) -> bool:
        """Rank 0 alone writes the run folder, logs and serves the viewer."""
        return self.rank == 0

    @property
    def is_distributed(self) -> bool:
        return self.size > 1

    # ------------------------------------------------------------------ collectives
    def all_reduce_sum_(self, tensors: Sequence[Tensor]) -> None:
        """Sum each tensor over the ranks, in place, in one all-reduce of a flat buffer (one
        collective per step instead of one per parameter). The tensors share a device and dtype."""
        if not self.is_distributed or not tensors:
            return
        flat = torch.cat([t.reshape(-1) for t in tensors])
        _collective(torch.distributed.all_reduce, flat)
        offset = 0
        for t in tensors:
            t.copy_(flat[offset:offset + t.numel()].view_as(t))
            offset += t.numel()

    def all_gather(self, tensor: Tensor) -> list[Tensor]:
        """The same-shaped ``tensor`` of every rank, in rank order."""
        if not self.is_distributed:
            return [tensor]
        out = [torch.empty_like(tensor) for _ in range(self.size)]
        _collective(torch.distributed.all_gather, out, tensor.contiguous())
        return out

    def all_gather_object(self, value: Any) -> list[Any]:
        """A picklable value of every rank, in rank order (small things: names, metrics)."""
        if not self.is_distributed:
            return [value]
        out: list[Any] = [None] * self.size
        _collective(torch.distributed.all_gather_object, out, value)
        return out

    def broadcast_object(self, value: Any) -> Any:
        """Rank 0's ``value`` on every rank."""
        if not self.is_distributed:
            return value
        box = [value]
        _collective(torch.distributed.broadcast_object_list, box, src=0)
        return box[0]

    def any_of(self, *flags: bool) -> tuple[bool, ...]:
        """For each flag, True on every rank when it is true on one (a stop request, a
        checkpoint that one rank's clock says is due); one collective for all of them."""
        if not self.is_distributed:
            return tuple(bool(f) for f in flags)
        values = torch.tensor([float(bool(f)) for f in flags], device=self.device)
        _collective(torch.distributed.all_reduce, values, op=torch.distributed.ReduceOp.MAX)
        return tuple(bool(v > 0) for v in values.tolist())

    def check_same(self, what: str, checksum: Tensor) -> None:
        """Raise :class:`DivergenceError` on every rank if the ranks' ``checksum`` [K] differ."""
        if not self.is_distributed:
            return
        values = self.all_gather_object(checksum.detach().to("cpu", torch.float64).tolist())
        if any(v != values[0] for v in values[1:]):
            ranks = [r for r, v in enumerate(values) if v != values[0]]
            raise DivergenceError(f"the ranks hold different {what}: rank(s) {ranks} differ from rank 0 "
                                  f"(checksums {values[0]} vs {values[ranks[0]]}); the run stops so that "
                                  f"the ranks never train different models")


def _collective(fn: Any, *args: Any, **kwargs: Any) -> None:
    try:
        fn(*args, **kwargs)
    except RuntimeError as err:  # gloo: "Connection closed by peer"; NCCL: a watchdog timeout
        reason = re.sub(r"^\[[^\]]*\]\s*", "", str(err).strip().splitlines()[0]).split(". ")[0][:200]
        raise PeerLostError(f"a collective operation failed, most likely because another rank "
                               f"stopped or died ({reason})") from err


def params_checksum(tensors: Sequence[Tensor]) -> Tensor:
    """A cheap fingerprint of parameter tensors: [2 K] float64 (sum and sum of |x| of each)."""
    parts = []
    for t in tensors:
        x = t.detach().to(torch.float64)
        parts += [x.sum(), x.abs().sum()]
    return torch.stack(parts) if parts else torch.zeros(0, dtype=torch.float64)


def init_world(device: torch.device, timeout_minutes: float = 10.0) -> tuple[World, torch.device]:
    """Join the process group that torchrun described in the environment, or be a world of one.

    Returns the world and this rank's device: with CUDA, ``cuda:LOCAL_RANK`` (one GPU per
    process); on the CPU, the CPU. NCCL on CUDA, gloo on the CPU. ``timeout_minutes`` bounds how
    long a collective waits for a silent rank before the run fails.
    """
    if not launched_by_torchrun():
        return World(), device
    stop_with_launcher()
    rank, size = int(os.environ["RANK"]), int(os.environ["WORLD_SIZE"])
    local_rank = int(os.environ.get("LOCAL_RANK", "0"))
    if size == 1:
        return World(rank, size, local_rank, str(device)), device
    if not torch.distributed.is_available():
        raise DistributedError("this torch build has no torch.distributed: train in one process")
    if device.type == "cuda":
        if local_rank >= torch.cuda.device_count():
            raise DistributedError(f"rank {rank} has local rank {local_rank} but this machine has "
                                   f"{torch.cuda.device_count()} CUDA device(s): start at most one "
                                   f"process per GPU (--nproc-per-node / --machine.num-devices)")
        device = torch.device("cuda", local_rank)
        torch.cuda.set_device(device)
        backend = "nccl"
    else:
        backend = "gloo"
    if not torch.distributed.is_initialized():
        torch.distributed.init_process_group(backend, timeout=datetime.timedelta(minutes=timeout_minutes))
    return World(rank, size, local_rank, str(device)), device


def leave_world(world: World) -> None:
    """Leave the process group at the end of a run (no-op for a world of one).

    The ranks first meet at a barrier, so that none closes its connections while another still
    uses them; then the group is destroyed and collected while the interpreter is fully alive
    (gloo's worker threads otherwise release their last tensors during interpreter shutdown and
    abort the process)."""
    if world.is_distributed and torch.distributed.is_initialized():
        try:
            torch.distributed.barrier()
        except RuntimeError:
            pass  # another rank is gone already: leave anyway
        torch.distributed.destroy_process_group()
        gc.collect()
