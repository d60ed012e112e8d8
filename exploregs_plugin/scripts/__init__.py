"""Console entry points (eg-train, eg-eval, eg-export, eg-render, eg-view, eg-scenes, eg-analyze, eg-bench)."""

from __future__ import annotations

import os
import sys
from typing import Any, Callable, TypeVar

from exploregs_plugin.configs import use_joined_help_lines
from exploregs_plugin.io.checkpoint import CheckpointError
from exploregs_plugin.threads import apply_threads

T = TypeVar("T")

use_joined_help_lines()  # --help: a docstring's sentences are not broken where the source wraps

USER_ERRORS: tuple[type[BaseException], ...] = (ValueError, FileNotFoundError, CheckpointError)
"""Problems with the user's input: reported as one clear line, not a traceback."""


def run_cli(command: str, main: Callable[[T], Any], args: T) -> Any:
    """Run ``main(args)``; a user error prints ``COMMAND: error: ...`` and exits with code 2.

    Set EXPLOREGS_DEBUG=1 to get the traceback instead. Every command computes with one thread per
    CPU this process may use (or OMP_NUM_THREADS); eg-train's --num-threads overrides it.
    """
    apply_threads()
    try:
        return main(args)
    except USER_ERRORS as err:
        if os.environ.get("EXPLOREGS_DEBUG"):
            raise
        print(f"{command}: error: {err}", file=sys.stderr)
        raise SystemExit(2) from err
