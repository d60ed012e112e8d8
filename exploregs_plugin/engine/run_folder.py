"""The folder a training run writes: its timestamped name, and one error naming it when it cannot
be written (read-only, full, missing permissions) instead of a traceback about one of its files.
Reading finished run folders is :mod:`exploregs_plugin.runs`."""

from __future__ import annotations

from contextlib import contextmanager
from datetime import datetime
from pathlib import Path
from typing import Iterator

from exploregs_plugin.io.atomic import create_new_folder


class RunFolderError(ValueError):
    """The run folder cannot be written (read-only, full, missing permissions)."""


def new_run_dir(output_dir: Path, scene: str, method: str) -> Path:
    """Create ``output_dir/scene/method/<timestamp>``; a run that started in the same second (and
    so made that name first) leaves this one ``<timestamp>-2``, ... (created atomically: two runs
    never share a folder and overwrite each other's checkpoints)."""
    default = output_dir / scene / method / datetime.now().strftime("%Y-%m-%d_%H%M%S")
    with run_folder_errors(default):
        return create_new_folder(default)


@contextmanager
def run_folder_errors(run_dir: Path) -> Iterator[None]:
    """An OSError about a file in ``run_dir`` (the error itself, or one it was raised from)
    becomes one RunFolderError naming the folder; other errors pass unchanged."""
    try:
        yield
    except OSError as err:
        cause: BaseException | None = err
        while cause is not None:
            name = getattr(cause, "filename", None)
            if isinstance(cause, OSError) and name is not None and _inside(Path(name), run_dir):
                reason = cause.strerror or str(cause)
                raise RunFolderError(f"cannot write the run folder {run_dir}: {reason} ({name})") from err
            cause = cause.__cause__ or cause.__context__
        raise


def _inside(path: Path, folder: Path) -> bool:
    try:
        path.resolve().relative_to(folder.resolve())
        return True
    except ValueError:
        return path.resolve() in folder.resolve().parents  # a parent that could not be created
