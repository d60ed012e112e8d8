"""The project's compiled CPU kernels: building them once, loading them.

``csrc/`` holds C++ kernels with OpenMP threads: the EWA projection (``project_cpu.cpp``), SH
colours (``sh_cpu.cpp``), tile binning and compositing (``composite_cpu.cpp``) of the ``cpp``
renderer backend, and the training loss, L1 and SSIM in one kernel (``photometric_cpu.cpp``),
each forward and backward; the training step's non-finite watch (``watch_cpu.cpp``); a split's rows in
the new order (``rows_cpu.cpp``); and the
Python module's table of them (``bindings.cpp``). The kernel units include only ATen's tensor
headers and the binding only torch's pybind11 casters: torch/extension.h, which pulls in all of
libtorch's C++ API, made each unit cost about five times the CPU time. They
are compiled on first use with PyTorch's extension machinery (``torch.utils.cpp_extension.load``,
ninja) into torch's extension cache (``$TORCH_EXTENSIONS_DIR``, default
``~/.cache/torch_extensions``), under a name that hashes the sources, the torch version and the
CPU, so a later run (or another process) loads them in about a second and a changed source or
machine builds anew. A machine that cannot build them gets one line saying why
(:func:`cpp_problem`), and the callers fall back to torch ops.

Determinism: every kernel writes each output element from one thread, in a fixed order (sums
over pixels per tile, per-tile parts added in a fixed order), so results are the same bit for bit
at any thread count (tested).
"""

from __future__ import annotations

import functools
import hashlib
import importlib.util
import io
import os
import platform
import shutil
import sys
import sysconfig
import threading
import time
from contextlib import redirect_stderr, redirect_stdout
from pathlib import Path
from typing import Any

import torch

SOURCES = [Path(__file__).parent / "csrc" / name
           for name in ("composite_cpu.cpp", "project_cpu.cpp", "sh_cpu.cpp", "photometric_cpu.cpp", "watch_cpu.cpp",
                        "rows_cpu.cpp", "bindings.cpp")]
HEADERS = [Path(__file__).parent / "csrc" / "tensors.h"]  # included by the units: part of the build's name
# -ffp-contract=off: no fused multiply-adds, so a vectorised and a scalar iteration of the same
# loop round alike (the forward and the backward's recomputation give the same T bit for bit).
CFLAGS = ["-O3", "-march=native", "-fopenmp", "-ffp-contract=off", "-fno-math-errno"]
LDFLAGS = ["-fopenmp"]


def _cpu_signature() -> str:
    """What -march=native compiles for: the CPU model and flags (a binary built on another CPU
    may use instructions this one lacks)."""
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return platform.processor() or platform.machine()
    lines = [ln for ln in text.splitlines() if ln.startswith(("model name", "flags"))]
    return "\n".join(sorted(set(lines)))


def extension_name() -> str:
    h = hashlib.sha256()
    for part in (*(p.read_bytes() for p in SOURCES + HEADERS), torch.__version__.encode(), _cpu_signature().encode(),
                 " ".join(CFLAGS).encode()):
        h.update(part)
    return f"exploregs_cpu_kernels_{h.hexdigest()[:12]}"


def _toolchain_problem() -> str | None:
    compiler = os.environ.get("CXX", "c++")
    if shutil.which(compiler) is None:
        return f"no C++ compiler found (looked for '{compiler}'; install g++ or set CXX)"
    if shutil.which("ninja") is None:
        try:
            import ninja  # the PyPI package, whose binary may not be on PATH (a venv not activated)
        except ImportError:
            return "ninja is not installed (pip install ninja)"
        os.environ["PATH"] = f"{ninja.BIN_DIR}{os.pathsep}{os.environ.get('PATH', '')}"
    include = sysconfig.get_paths().get("include")
    if not include or not (Path(include) / "Python.h").exists():
        return f"the Python headers are missing (no Python.h in {include}; install python3-dev)"
    return None


def _build_dir(name: str) -> Path | None:
    """torch's extension cache folder for ``name`` (None if torch's private helper changed)."""
    from torch.utils.cpp_extension import _get_build_directory

    try:
        return Path(_get_build_directory(name, verbose=False))
    except Exception:
        return None


def _import_built(name: str, folder: Path) -> Any:
    """The built module, imported straight from the cache: no build lock, no ninja run. (torch's
    ``load`` takes a lock file even for a finished build, and a process killed while holding it,
    say by Ctrl-C at start, leaves the lock behind for every later process to wait on.)"""
    spec = importlib.util.spec_from_file_location(name, folder / f"{name}.so")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


# A build lock older than this is left over from a killed process (a build takes well under a
# minute of CPU time on a usual 2-core machine; a slow one may take a few).
STALE_LOCK_SECONDS = 600
PROGRESS_SECONDS = 15.0
"""While the kernels build, a line at least this often (and one per finished unit), so that a
slow machine does not look hung."""


def _elapsed(seconds: float) -> str:
    return f"{int(seconds) // 60}:{int(seconds) % 60:02d}"


class _BuildProgress:
    """Prints, from a thread, a line per compiled unit (its object file appears in the build
    folder) and a line every PROGRESS_SECONDS between them, with the elapsed time."""

    def __init__(self, folder: Path | None, units: list[str]) -> None:
        self.folder, self.units = folder, units
        self.out = sys.stderr  # taken before the build redirects sys.stderr into its log
        self.started = time.monotonic()
        self.done: set[str] = set()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="kernel-build-progress", daemon=True)

    def _finished_units(self) -> set[str]:
        if self.folder is None:
            return set()
        return {u for u in self.units if (self.folder / f"{u}.o").exists()}

    def _say(self, text: str) -> None:
        print(f"  [{_elapsed(time.monotonic() - self.started)}] {text}", file=self.out, flush=True)

    def _run(self) -> None:
        last = time.monotonic()
        while not self._stop.wait(0.5):
            finished = self._finished_units() - self.done
            for unit in sorted(finished):
                self.done.add(unit)
                self._say(f"compiled {unit} ({len(self.done)} of {len(self.units)} units)")
                last = time.monotonic()
            if time.monotonic() - last >= PROGRESS_SECONDS:
                self._say(f"compiling... {len(self.done)} of {len(self.units)} units done")
                last = time.monotonic()

    def __enter__(self) -> "_BuildProgress":
        self.done = self._finished_units()  # left by an interrupted build: ninja keeps them
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()


def _clear_stale_lock(folder: Path) -> None:
    lock = folder / "lock"
    try:
        age = time.time() - lock.stat().st_mtime
    except OSError:
        return
    if age > STALE_LOCK_SECONDS:
        print(f"removing a stale build lock ({age / 60:.0f} min old): {lock}", file=sys.stderr, flush=True)
        lock.unlink(missing_ok=True)


@functools.lru_cache(maxsize=1)
def _load() -> tuple[Any, str | None]:
    """(module, None) when the extension builds and loads, else (None, one-line reason)."""
    name = extension_name()
    folder = _build_dir(name)
    if folder is not None and (folder / f"{name}.so").exists():
        try:
            return _import_built(name, folder), None
        except Exception:  # a damaged build: build it again below
            pass
    problem = _toolchain_problem()
    if problem is not None:
        return None, problem
    from torch.utils.cpp_extension import load

    if folder is not None:
        _clear_stale_lock(folder)
    units = [p.stem for p in SOURCES]
    print(f"building the compiled CPU kernels: {len(units)} C++ units, once per machine and version "
          f"(about 33 s of CPU time, measured on a 2-core machine; docs/training.md)", file=sys.stderr, flush=True)
    log = io.StringIO()
    progress = _BuildProgress(folder, units)
    try:
        # the progress thread prints to the real stderr, captured before the redirection
        with progress, redirect_stdout(log), redirect_stderr(log):
            module = load(name=name, sources=[str(p) for p in SOURCES], extra_cflags=CFLAGS,
                          extra_ldflags=LDFLAGS, verbose=False)  # fmt: skip
    except Exception as err:  # a failed build is reported as one line, never a traceback
        text = (str(err) + "\n" + log.getvalue()).strip().splitlines()
        # the compiler's first "error:" line says more than torch's "Error building extension"
        reason = next((ln.strip() for ln in text if "error:" in ln), text[0] if text else repr(err))
        return None, f"the C++ kernels did not build: {reason[:300]}"
    print(f"built the compiled CPU kernels in {_elapsed(time.monotonic() - progress.started)} "
          f"(cached in {folder})", file=sys.stderr, flush=True)
    return module, None


def cpp_problem() -> str | None:
    """Why the compiled CPU kernels cannot be used here (one line), or None (they are built and loaded)."""
    return _load()[1]


def extension() -> Any:
    module, problem = _load()
    if module is None:
        raise RuntimeError(problem)
    return module
