"""Console entry points (eg-train, eg-eval, eg-export, eg-render, eg-view, eg-scenes, eg-analyze, eg-bench)."""

from __future__ import annotations

import contextlib
import io
import os
import sys
import warnings
from functools import partial
from typing import Any, Callable, TypeVar

from exploregs_plugin.io.config_files import tyro_error_text, use_joined_help_lines
from exploregs_plugin.io.checkpoint import CheckpointError
from exploregs_plugin.runtime.threads import apply_threads

T = TypeVar("T")

use_joined_help_lines()  # --help: a docstring's sentences are not broken where the source wraps

USER_ERRORS: tuple[type[BaseException], ...] = (ValueError, FileNotFoundError, CheckpointError)
"""Problems with the user's input: reported as one clear line, not a traceback."""


def parse_cli(command: str, spec: Any, description: str, argv: list[str] | None = None) -> Any:
    """``tyro.cli(spec)`` with a wrong command line as one line, ``COMMAND: error: ...`` (a flag of
    another command, a missing path, a value of the wrong type), exit code 2; --help as tyro writes it."""
    import tyro

    captured = io.StringIO()
    try:
        with contextlib.redirect_stderr(captured):
            return tyro.cli(spec, args=argv, description=description)
    except SystemExit as exit_:
        if exit_.code in (0, None):
            sys.stderr.write(captured.getvalue())
            raise
        text = tyro_error_text(captured.getvalue()) or f"invalid arguments {argv if argv is not None else sys.argv[1:]}"
        hint = f" ({command} --help lists its options)" if text.startswith(("unrecognized", "missing")) else ""
        print(f"{command}: error: {text}{hint}", file=sys.stderr)
        raise SystemExit(2) from None


def run_cli(command: str, main: Callable[[T], Any], args: T) -> Any:
    """Run ``main(args)``; a user error prints ``COMMAND: error: ...`` and exits with code 2.

    Set EXPLOREGS_DEBUG=1 to get the traceback instead. Every command computes with one thread per
    CPU this process may use (or OMP_NUM_THREADS); eg-train's --num-threads overrides it. A warning
    prints as one line, ``COMMAND: warning: ...`` (Python's own form adds the file, line number and
    source line of the code that warned, which tell a user nothing); EXPLOREGS_DEBUG keeps that form.
    """
    apply_threads()
    formatted = warnings.formatwarning
    if not os.environ.get("EXPLOREGS_DEBUG"):
        warnings.formatwarning = partial(_one_line_warning, command)
    try:
        return main(args)
    except USER_ERRORS as err:
        if os.environ.get("EXPLOREGS_DEBUG"):
            raise
        print(f"{command}: error: {err}", file=sys.stderr)
        raise SystemExit(2) from err
    finally:
        warnings.formatwarning = formatted


def _one_line_warning(command: str, message: Warning | str, category: type[Warning], filename: str, lineno: int,
                      line: str | None = None) -> str:
    return f"{command}: warning: {message}\n"
