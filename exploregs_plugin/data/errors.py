"""The one exception type for bad datasets, so callers can catch data problems specifically."""

from __future__ import annotations

from pathlib import Path


class DataError(ValueError):
    """A dataset on disk (or a data argument) is unusable.

    The message always names the file or argument and says what is wrong with it.
    """

    def __init__(self, where: str | Path, problem: str) -> None:
        self.where = str(where)
        self.problem = problem
        super().__init__(f"{where}: {problem}")


def dataset_folder(root: str | Path) -> Path:
    """``root`` as a Path, checked to be an existing folder."""
    root = Path(root)
    if not root.is_dir():
        raise DataError(root, "dataset folder does not exist")
    return root
