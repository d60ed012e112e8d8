"""Which renderer draws: ``RasterSettings.backend`` = auto, torch, cpp or gsplat.

``auto`` (the default) picks gsplat's CUDA kernels on a CUDA device when gsplat is installed and
the settings allow them, the compiled CPU compositor on the CPU when it builds, and the pure-torch
reference otherwise. A backend named explicitly that cannot run is one clear error
(:func:`backend_problem`); ``auto`` never fails, and :func:`backend_line` says what it chose and why.
"""

from __future__ import annotations

import functools

import torch

from .cpp_backend import cpp_problem
from .gsplat_backend import gsplat_problem
from .settings import RasterSettings

BACKENDS = ("auto", "torch", "cpp", "gsplat")


def _cpp_problem(device: torch.device) -> str | None:
    if device.type != "cpu":
        return (f"--model.raster.backend cpp is the compiled CPU compositor, and this run's device is {device}: "
                f"use --device cpu, or --model.raster.backend gsplat or torch on a GPU")
    problem = cpp_problem()
    return None if problem is None else f"--model.raster.backend cpp cannot run here: {problem}"


@functools.lru_cache(maxsize=32)
def backend_problem(settings: RasterSettings, device: torch.device) -> str | None:
    """Why ``settings.backend`` cannot render on ``device`` (one line), or None when it can.
    Cached: every render asks it, and the answer depends on its arguments alone."""
    name = settings.backend
    if name in ("auto", "torch"):
        return None
    if name == "cpp":
        return _cpp_problem(device)
    if name == "gsplat":
        return gsplat_problem(settings, device)
    return f"unknown rasterizer backend {name!r}; choose one of {', '.join(BACKENDS)}"


@functools.lru_cache(maxsize=32)
def _resolve(settings: RasterSettings, device: torch.device) -> tuple[str, str]:
    if settings.backend != "auto":
        return settings.backend, "chosen with --model.raster.backend"
    if device.type == "cuda":
        problem = gsplat_problem(settings, device)
        return ("gsplat", "gsplat's CUDA kernels") if problem is None else ("torch", f"gsplat not used: {problem}")
    if device.type == "cpu":
        problem = cpp_problem()
        return ("cpp", "compiled CPU kernels") if problem is None else ("torch", f"cpp not used: {problem}")
    return "torch", f"the pure-torch reference (no compiled backend for {device.type})"


def resolve_backend(settings: RasterSettings, device: torch.device) -> str:
    """The backend that renders on ``device``: ``settings.backend``, or the choice of ``auto``."""
    return _resolve(settings, torch.device(device))[0]


def backend_line(settings: RasterSettings, device: torch.device) -> str:
    """One line for the start of a run: the renderer and why it was chosen."""
    name, why = _resolve(settings, torch.device(device))
    return f"renderer: {name} ({why})"
