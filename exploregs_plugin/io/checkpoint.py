"""Checkpoints written atomically: a crash, Ctrl-C or a full disk never replaces a good one.

Layout: ``RUN_DIR/checkpoints/step-XXXXXXX.pt``; the number is the next step to run.
"""

from __future__ import annotations

import os
import re
import shlex
import sys
from pathlib import Path
from typing import Any, Callable

import torch

CHECKPOINT_DIR = "checkpoints"
DATASET_MARKS = ("sparse", "images", "transforms.json", "transforms_train.json", "poses_bounds.npy")
"""What a dataset folder holds (the layouts of docs/data.md), to say so when one is passed as a run."""
RUN_CONFIG = "config.yml"  # what makes a folder a run folder (the trainer writes it first)
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
    its previous content. A failed write (an OSError, or the RuntimeError that torch.save makes of
    the OSError of a full disk) raises :class:`CheckpointError` naming the reason.
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
        if isinstance(err, (OSError, RuntimeError)):
            raise CheckpointError(f"could not write checkpoint {path}: {_write_failure(err)}") from err
        raise


def _write_failure(err: BaseException) -> str:
    """The reason of a failed write: the OSError behind it (torch.save raises a RuntimeError such as
    "unexpected pos 704 vs 598" whose context is the file's OSError), else the error's first line."""
    cause: BaseException | None = err
    while cause is not None:
        if isinstance(cause, OSError):
            return cause.strerror or str(cause)
        cause = cause.__cause__ or cause.__context__
    return str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__


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
        if path.suffix.lower() == ".ply":
            raise CheckpointError(f"{path} is a PLY of Gaussians, not a run folder or a checkpoint (.pt) of one")
        if path.suffix != ".pt":
            raise CheckpointError(f"{path} is neither a run folder nor a checkpoint file (.pt)")
        run_dir = path.parent.parent if path.parent.name == CHECKPOINT_DIR else path.parent
        return run_dir, path
    if path.is_dir():
        check_run_folder(path)
        return path, latest_checkpoint(path)
    raise CheckpointError(f"{path} is neither a run folder nor a checkpoint file")


def is_dataset_folder(path: Path) -> bool:
    """Whether the folder ``path`` holds a dataset (and is not a run folder)."""
    path = Path(path)
    return not (path / RUN_CONFIG).is_file() and any((path / mark).exists() for mark in DATASET_MARKS)


def dataset_around(path: Path) -> Path | None:
    """The dataset a folder we would write to belongs to: ``path`` itself when it is a dataset
    folder, or the dataset whose images/ or sparse/ (any mark folder) holds it; None otherwise.
    (Only the mark folders count: a folder beside a dataset's images is not inside it.)"""
    path = Path(path).expanduser().resolve()
    if path.is_dir() and is_dataset_folder(path):
        return path
    for inner, parent in zip([path, *path.parents], path.parents):
        if inner.name in DATASET_MARKS and is_dataset_folder(parent):
            return parent
    return None


def check_output_folder(flag: str, path: Path) -> None:
    """Refuse to write outputs into a dataset (:func:`dataset_around`): one line naming both."""
    dataset = dataset_around(path)
    if dataset is not None:
        where = "is a dataset" if dataset == Path(path).expanduser().resolve() else f"is inside the dataset {dataset}"
        raise CheckpointError(f"{flag} {path} {where}; outputs never go into a dataset: pass a folder of its own "
                              f"as {flag}")


def check_run_folder(path: Path) -> None:
    """Raise :class:`CheckpointError` when the folder ``path`` is not a run folder (no config.yml),
    naming the newest run inside it when there is one (``outputs/SCENE`` instead of a run)."""
    path = Path(path)
    if (path / RUN_CONFIG).is_file():
        return
    if is_dataset_folder(path):
        raise CheckpointError(f"{path} is a dataset, not a run folder (it has no {RUN_CONFIG}): "
                              f"eg-train METHOD --data {shlex.quote(str(path))} trains a run on it")
    inside = [c.parent for depth in ("*", "*/*", "*/*/*") for c in path.glob(f"{depth}/{RUN_CONFIG}")]
    hint = ""
    if inside:
        newest = max(inside, key=lambda run: (run / RUN_CONFIG).stat().st_mtime)
        hint = f"; it holds {len(inside)} run(s), the newest {newest}"
    raise CheckpointError(f"{path} is not a run folder (it has no {RUN_CONFIG}): pass a folder that eg-train "
                          f"wrote, outputs/<scene>/<method>/<timestamp>, or a checkpoint file in one{hint}")


def _print_note(text: str) -> None:
    print(text, file=sys.stderr)


def load_run_checkpoint(path: Path, note: Callable[[str], None] | None = _print_note
                        ) -> tuple[Path, Path, dict[str, Any]]:
    """A run folder or one checkpoint file -> (run_dir, checkpoint_file, its payload).

    For a run folder, the newest checkpoint that reads whole: one that does not (truncated by a
    crash of the machine or a full disk outside the atomic write, or damaged in a copy) is
    skipped for the one before it, and ``note`` is told which was skipped and which was taken.
    A checkpoint file named explicitly is read as it is.
    """
    path = Path(path)
    run_dir, newest = resolve_run(path)
    if not path.is_dir():
        return run_dir, newest, load_checkpoint(newest)
    bad: list[str] = []
    for candidate in reversed(list_checkpoints(run_dir)):
        try:
            payload = load_checkpoint(candidate)
        except CheckpointError:
            bad.append(candidate.name)
            continue
        if bad and note is not None:
            note(f"note: checkpoint {', '.join(bad)} of {run_dir} cannot be read (truncated or corrupt); "
                 f"using the previous good one, {candidate.name}")
        return run_dir, candidate, payload
    raise CheckpointError(f"no checkpoint of {run_dir} can be read ({', '.join(bad)}: truncated or corrupt); "
                          f"start the run again (its settings are in {run_dir / RUN_CONFIG})")
