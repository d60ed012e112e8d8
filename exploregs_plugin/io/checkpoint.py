"""Checkpoints written atomically: a crash, Ctrl-C or a full disk never replaces a good one.

Layout: ``RUN_DIR/checkpoints/step-XXXXXXX.pt``; the number is the next step to run.
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Any

import torch

CHECKPOINT_DIR = "checkpoints"
_NAME = re.compile(r"^step-(\d{7,})\.pt$")


class CheckpointError(RuntimeError):
    """A checkpoint could not be written or read."""


def checkpoint_path(run_dir: Path, step: int) -> Path:
    return Path(run_dir) / CHECKPOINT_DIR / f"step-{step:07d}.pt"


def list_checkpoints(run_dir: Path) -> list[Path]:
    """Checkpoints of a run, oldest first."""
    folder = Path(run_dir) / CHECKPOINT_DIR
    if not folder.is_dir():
        return []
    found = [(int(m.group(1)), p) for p in folder.iterdir() if (m := _NAME.match(p.name))]
    return [p for _, p in sorted(found)]


def _fsync_dir(folder: Path) -> None:
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def atomic_torch_save(payload: Any, path: Path) -> None:
    """torch.save to a temporary file in the same folder, fsync, then rename over ``path``.

    On any failure (disk full, interruption) the temporary file is removed and ``path`` keeps
    its previous content.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        with open(tmp, "wb") as f:
            torch.save(payload, f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
        _fsync_dir(path.parent)
    except BaseException as err:
        tmp.unlink(missing_ok=True)
        if isinstance(err, OSError):
            raise CheckpointError(f"could not write checkpoint {path}: {err}") from err
        raise


def save_checkpoint(run_dir: Path, step: int, payload: dict[str, Any], keep_last: int) -> Path:
    """Write ``payload`` as the checkpoint for ``step``; keep only the newest ``keep_last``."""
    path = checkpoint_path(run_dir, step)
    atomic_torch_save(payload, path)
    if keep_last > 0:
        for old in list_checkpoints(run_dir)[:-keep_last]:
            old.unlink(missing_ok=True)
    return path


def load_checkpoint(path: Path) -> dict[str, Any]:
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint not found: {path}")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as err:  # torch raises several types for truncated or foreign files
        raise CheckpointError(f"checkpoint {path} is unreadable or corrupt: {err}") from err
    if not isinstance(payload, dict) or "step" not in payload or "params" not in payload:
        raise CheckpointError(f"{path} is not an ExploreGS checkpoint")
    return payload


def latest_checkpoint(run_dir: Path) -> Path:
    found = list_checkpoints(run_dir)
    if not found:
        raise CheckpointError(
            f"no checkpoints in {Path(run_dir) / CHECKPOINT_DIR}: the run stopped before its first one, so there "
            f"is nothing to resume; start it again (its settings are in {Path(run_dir) / 'config.yml'})")
    return found[-1]


def resolve_run(path: Path) -> tuple[Path, Path]:
    """Accept a run folder or a checkpoint file; return (run_dir, checkpoint_file)."""
    path = Path(path)
    if path.is_file():
        run_dir = path.parent.parent if path.parent.name == CHECKPOINT_DIR else path.parent
        return run_dir, path
    if path.is_dir():
        return path, latest_checkpoint(path)
    raise CheckpointError(f"{path} is neither a run folder nor a checkpoint file")
