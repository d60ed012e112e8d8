"""Small text files written atomically: a temporary file in the same folder, then a rename; and
new folders claimed atomically.

A crash, Ctrl-C or a full disk leaves either the old file or the new one, never half of one.
(Checkpoints use :func:`exploregs_plugin.io.checkpoint.atomic_torch_save`, which also fsyncs.)
"""

from __future__ import annotations

import os
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator


@contextmanager
def atomic_path(path: Path) -> Iterator[Path]:
    """A temporary name beside ``path`` (parents created) to write to: renamed to ``path`` when
    the block ends normally, removed when it raises, so ``path`` keeps its old content then."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def atomic_write_text(path: Path, text: str, newline: str | None = None) -> None:
    """Write ``text`` to ``path`` (parents created); on failure ``path`` keeps its old content."""
    with atomic_path(path) as tmp, open(tmp, "w", newline=newline) as f:
        f.write(text)


def create_new_folder(path: Path) -> Path:
    """Create ``path`` (parents too) and return it; when it exists already, create and return the
    first free ``path-2``, ``path-3``, ...

    ``mkdir`` without exist_ok either creates the folder or fails, in one step of the file system,
    so two processes that ask for the same name at once (two runs started in the same second)
    never both get it.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    candidate, n = path, 1
    while True:
        try:
            candidate.mkdir()
            return candidate
        except FileExistsError:
            n += 1
            candidate = path.with_name(f"{path.name}-{n}")
