"""``eg-train --machine.num-devices N``: start the ranks of a data-parallel run on this machine.

The ranks are started by torch's elastic launcher, the engine of ``torchrun``: each one runs
``python -m exploregs_plugin.scripts.train`` with the same arguments and the environment that
torchrun gives (RANK, WORLD_SIZE, LOCAL_RANK, rendezvous address), so ``eg-train ...
--machine.num-devices 2`` and ``torchrun --nproc-per-node 2 -m exploregs_plugin.scripts.train ...``
are the same run. One machine rendezvouses on a free local port; several use torchrun's static
rendezvous at ``--machine.master-addr:--machine.master-port`` with ``--machine.machine-rank``.
When a rank fails the launcher stops the others and this command ends with one line naming it.
"""

from __future__ import annotations

import os
import socket
import sys
import uuid

from exploregs_plugin.distributed import MachineConfig


class LaunchError(RuntimeError):
    """A rank of the run failed; the message names it and how it ended."""


def free_port(host: str = "127.0.0.1") -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind((host, 0))
        return int(sock.getsockname()[1])


def ranks_threads(num_devices: int, cpus: int | None = None) -> int:
    """CPU threads per rank when the ranks share this machine's cores (at least one)."""
    return max(1, (cpus or os.cpu_count() or 1) // num_devices)


def launch(machine: MachineConfig, argv: list[str]) -> None:
    """Run ``eg-train argv`` as ``machine.num_devices`` ranks here (of ``machine.world_size``).

    Raises :class:`LaunchError` when a rank fails (the others are stopped first)."""
    from torch.distributed.elastic.multiprocessing.errors import ChildFailedError
    from torch.distributed.launcher.api import LaunchConfig, elastic_launch

    # One setting governs the threads: ranks sharing the cores split them (torchrun does the same
    # with OMP_NUM_THREADS); an explicit --num-threads or OMP_NUM_THREADS is kept.
    os.environ.setdefault("OMP_NUM_THREADS", str(ranks_threads(machine.num_devices)))
    several = machine.num_machines > 1
    port = machine.master_port or free_port(machine.master_addr)
    config = LaunchConfig(
        min_nodes=machine.num_machines,
        max_nodes=machine.num_machines,
        nproc_per_node=machine.num_devices,
        run_id=f"exploregs-{port}" if several else f"exploregs-{uuid.uuid4().hex[:8]}",
        rdzv_backend="static" if several else "c10d",
        rdzv_endpoint=f"{machine.master_addr}:{port}",
        rdzv_configs={"rank": machine.machine_rank} if several else {},
        max_restarts=0,
        monitor_interval=0.2,
    )
    try:
        elastic_launch(config, sys.executable)("-m", "exploregs_plugin.scripts.train", *argv)
    except ChildFailedError as err:
        rank, failure = err.get_first_failure()
        how = failure.signal_name() if failure.exitcode < 0 else f"exit code {failure.exitcode}"
        raise LaunchError(f"rank {rank} (pid {failure.pid}) failed with {how}; the other ranks were stopped. "
                          f"Checkpoints are written atomically: continue the run folder printed above with "
                          f"eg-train --resume RUN_DIR") from None
