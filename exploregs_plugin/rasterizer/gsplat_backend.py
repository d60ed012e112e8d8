"""gsplat's CUDA kernels behind the rasterizer's call shape (``RasterSettings.backend = "gsplat"``).

The conventions we can set are ours: pixel centres at +0.5, the 0.3 px low-pass (``eps2d``),
the guard band 0.3, the alpha floor 1/255, the transmittance stop 1e-4, the antialiased
variant, SH colours max(SH + 0.5, 0), the background and the expected depth sum w z / A.
gsplat 1.5.3's kernels fix three things differently (read from its CUDA sources): alpha is
capped at 0.999 (ours: 0.99); the support box is per axis min(3.33, sqrt(2 ln(255 o)))
standard deviations (ours: min(3, sqrt(2 ln(255 o))), which leaves out only pairs below the alpha
floor, and the ``radii`` the strategies see are 3 standard deviations), and Gaussians with
o < 1/255 are culled; and a pixel blends every Gaussian whose box meets its tile (ours: whose box holds the
pixel centre). Images therefore agree closely but not to float rounding, mostly at support
edges and where alpha saturates. The returned ``info`` keeps
the contract the strategies read: ``means2d`` (whose gradient is the densification statistic;
[1, N, 2], the tensor gsplat differentiates), ``radii`` [N, 2], ``visible`` [N], ``depths``,
``conics``, ``camera_center``, ``width``, ``height``, ``n_cameras`` and ``n_pairs``.
"""

from __future__ import annotations

import functools
import importlib.util
from dataclasses import fields
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from .settings import RasterSettings

INSTALL_HINT = 'pip install -e ".[gpu]"'
# Settings gsplat's kernels hard-code: a run that changes them from our defaults cannot be honoured.
_KERNEL_FIXED = ("sigma_radius", "guard_band", "alpha_max", "alpha_min", "transmittance_min")


class BackendError(ValueError):
    """A renderer backend that cannot run with these settings or on this machine."""


@functools.lru_cache(maxsize=32)
def gsplat_problem(settings: RasterSettings, device: torch.device) -> str | None:
    """Why gsplat's kernels cannot render with ``settings`` on ``device`` (one line), or None."""
    if importlib.util.find_spec("gsplat") is None:
        return f"--model.raster.backend gsplat needs the gsplat package: {INSTALL_HINT}"
    if device.type != "cuda":
        return (f"--model.raster.backend gsplat renders with CUDA kernels, and this run's device is {device}: "
                f"use --device cuda on a machine with a GPU, or --model.raster.backend torch")
    if settings.visibility_stats:
        return ("--model.raster.visibility-stats (occlusion-aware splitting) needs the per-Gaussian sums that only "
                "--model.raster.backend cpp or torch compute")
    defaults = {f.name: f.default for f in fields(RasterSettings)}
    for name in _KERNEL_FIXED:
        if getattr(settings, name) != defaults[name]:
            return (f"--model.raster.{name.replace('_', '-')} {getattr(settings, name)}: gsplat's kernels fix this "
                    f"constant; keep the default {defaults[name]} or use --model.raster.backend torch")
    return None


@functools.cache
def load_gsplat_kernels() -> Any:
    """gsplat's compiled kernels, imported once per process and one process at a time per machine.

    gsplat 1.5.3 builds its kernels on first import (minutes) and, finding no finished build,
    first deletes its build folder: a second process importing meanwhile (bench jobs, a run's
    ranks, test workers) would delete the first one's half-built files and both builds fail. Under
    an exclusive lock beside that folder the first process builds and the others wait, then load."""
    try:
        import fcntl
    except ImportError:  # no POSIX locks (Windows): import unguarded
        fcntl = None
    from torch.utils.cpp_extension import _get_build_directory

    # torch makes the build folder if it is missing, so its parent, where the lock lives, exists
    lock_dir = Path(_get_build_directory("gsplat_cuda", verbose=False)).parent
    with open(lock_dir / "gsplat_cuda.build-lock", "a") as lock:
        if fcntl is not None:
            fcntl.flock(lock.fileno(), fcntl.LOCK_EX)
        try:
            from gsplat.cuda._backend import _C
        finally:
            if fcntl is not None:
                fcntl.flock(lock.fileno(), fcntl.LOCK_UN)
    return _C


def rasterize_gsplat(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    sh_coeffs: Tensor | None,
    colors: Tensor | None,
    degree: int,
    viewmat: Tensor,
    K: Tensor,
    width: int,
    height: int,
    background: Tensor | None,
    near_plane: float,
    far_plane: float,
    settings: RasterSettings,
) -> tuple[Tensor, Tensor, Tensor, dict[str, Any]]:
    """:func:`exploregs_plugin.rasterizer.rasterize` through ``gsplat.rasterization`` (one camera).

    Arguments as there (already validated); ``degree`` is the active SH degree, -1 with ``colors``.
    """
    problem = gsplat_problem(settings, means.device)
    if problem is not None:
        raise BackendError(problem)
    load_gsplat_kernels()
    from gsplat import rasterization

    viewmat, K = viewmat.to(means), K.to(means)
    feats = colors if degree < 0 else sh_coeffs
    renders, alphas, meta = rasterization(
        means, quats, scales, opacities, feats, viewmat[None], K[None], width, height,
        near_plane=near_plane, far_plane=far_plane, eps2d=settings.eps2d,
        sh_degree=None if degree < 0 else degree, packed=False, tile_size=settings.tile_size,
        render_mode="RGB+ED", rasterize_mode="antialiased" if settings.antialiased else "classic",
        absgrad=settings.absgrad,  # gsplat leaves the sums on meta["means2d"].absgrad, as our renderers do
    )  # fmt: skip
    image, depth, acc = renders[0, ..., :3], renders[0, ..., 3:4], alphas[0]
    if background is not None:
        image = image + (1.0 - acc) * background.to(means)
    radii = meta["radii"][0]  # [N, 2] int32
    info: dict[str, Any] = {
        "means2d": meta["means2d"],  # [1, N, 2]: gsplat differentiates this tensor, not a view of it
        "radii": radii,
        "visible": (radii > 0).all(dim=-1),
        "depths": meta["depths"][0],
        "conics": meta["conics"][0],
        "camera_center": -(viewmat[:3, :3].T @ viewmat[:3, 3]),
        "width": width,
        "height": height,
        "n_cameras": 1,
        "n_pairs": int(meta["flatten_ids"].numel()) if "flatten_ids" in meta else -1,
    }
    return image, acc, depth, info
