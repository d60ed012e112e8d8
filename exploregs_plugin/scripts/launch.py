"""``eg-train --machine.num-devices N``: start the ranks of a data-parallel run on this machine.

The ranks are started by torch's elastic launcher, the engine of ``torchrun``: each one runs
``python -m exploregs_plugin.scripts.train`` with the same arguments and the environment that
torchrun gives (RANK, WORLD_SIZE, LOCAL_RANK, rendezvous address), so ``eg-train ...
--machine.num-devices 2`` and ``torchrun --nproc-per-node 2 -m exploregs_plugin.scripts.train ...``
are the same run. One machine rendezvouses on a free local port; several use torchrun's static
rendezvous at ``--machine.master-addr:--machine.master-port`` with ``--machine.machine-rank``.
When a rank fails the launcher stops the others and this command ends with one line naming it.
Ctrl-C or SIGTERM to this command reaches the ranks (torch's launcher passes it on), which
checkpoint and stop together; rank 0 prints the one stop line. The ranks stop too when this
command is killed outright (see :func:`exploregs_plugin.runtime.distributed.stop_with_launcher`).
"""

from __future__ import annotations

import contextlib
import logging
import os
import shlex
import signal
import socket
import sys
import tempfile
import uuid
from pathlib import Path
from typing import Iterator

from exploregs_plugin.runtime.distributed import LAUNCHER_PID, MachineConfig
from exploregs_plugin.io.checkpoint import list_checkpoints
from exploregs_plugin.runtime.threads import available_cpus

RUN_DIR_NOTE = "EXPLOREGS_RUN_DIR_NOTE"
"""A file where rank 0 writes its run folder, for the launcher's last line."""


class LaunchError(RuntimeError):
    """A rank of the run failed; the message names it and how it ended."""


class LaunchStopped(KeyboardInterrupt):
    """The launcher got SIGINT or SIGTERM and the ranks stopped on it (rank 0 said where)."""

    def __init__(self, signum: int) -> None:
        super().__init__(f"stopped by {signal.Signals(signum).name}")
        self.exit_code = 128 + signum


def free_port(host: str = "127.0.0.1") -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind((host, 0))
        return int(sock.getsockname()[1])


def ranks_threads(num_devices: int, cpus: int | None = None) -> int:
    """CPU threads per rank when the ranks share the CPUs this process may use (at least one)."""
    return max(1, (cpus or available_cpus()) // num_devices)


def note_run_dir(run_dir: Path) -> None:
    """Rank 0 of a launched run: tell the launcher the run folder (for its resume hint)."""
    note = os.environ.get(RUN_DIR_NOTE)
    if note:
        with contextlib.suppress(OSError):
            Path(note).write_text(str(run_dir))


def resume_hint(note: Path, several: bool = False) -> str:
    """How to go on after a failed rank: resume when the run has a checkpoint, else start again."""
    try:
        run_dir = Path(note.read_text().strip())
    except OSError:
        if several:  # rank 0, which names the folder, runs on machine 0
            return "if the run folder printed on machine 0 has a checkpoint, continue it with eg-train --resume RUN_DIR"
        return "no run folder was made yet: start the run again"
    if list_checkpoints(run_dir):
        return f"continue with: eg-train --resume {shlex.quote(str(run_dir))}"
    return f"no checkpoint was written yet: start the run again ({run_dir / 'config.yml'} holds its settings)"


@contextlib.contextmanager
def _quiet_launcher_logs() -> Iterator[None]:
    """torch's launcher logs every signal it passes on and every rank it stops; the command says
    what happened in one line instead (LOGLEVEL=INFO shows them again)."""
    if os.environ.get("LOGLEVEL"):
        yield
        return
    elastic = logging.getLogger("torch.distributed.elastic")
    null, propagate = logging.NullHandler(), elastic.propagate
    elastic.addHandler(null)
    elastic.propagate = False
    try:
        yield
    finally:
        elastic.removeHandler(null)
        elastic.propagate = propagate


def launch(machine: MachineConfig, argv: list[str]) -> None:
    """Run ``eg-train argv`` as ``machine.num_devices`` ranks here (of ``machine.world_size``).

    Raises :class:`LaunchError` when a rank fails (the others are stopped first), and
    :class:`LaunchStopped` when this command got SIGINT or SIGTERM (the ranks stopped on it)."""
    from torch.distributed.elastic.multiprocessing.api import SignalException
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
    os.environ[LAUNCHER_PID] = str(os.getpid())
    several_note = f" ({machine.world_size} in all)" if several else ""
    with tempfile.TemporaryDirectory(prefix="exploregs-launch-") as folder, _quiet_launcher_logs():
        note = Path(folder) / "run_dir"
        os.environ[RUN_DIR_NOTE] = str(note)
        print(f"launched {machine.num_devices} ranks{several_note}", file=sys.stderr)
        try:
            elastic_launch(config, sys.executable)("-m", "exploregs_plugin.scripts.train", *argv)
        except SignalException as err:
            raise LaunchStopped(int(err.sigval)) from None
        except ChildFailedError as err:
            rank, failure = err.get_first_failure()
            how = failure.signal_name() if failure.exitcode < 0 else f"exit code {failure.exitcode}"
            raise LaunchError(f"rank {rank} (pid {failure.pid}) failed with {how}; the other ranks were stopped; "
                              f"{resume_hint(note, several)}") from None
        finally:
            os.environ.pop(RUN_DIR_NOTE, None)
            os.environ.pop(LAUNCHER_PID, None)
