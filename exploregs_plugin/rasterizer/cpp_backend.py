"""The compiled CPU compositor (``RasterSettings.backend = "cpp"``): building it, and its autograd Function.

``csrc/composite_cpu.cpp`` holds tile binning and front-to-back compositing, forward and backward,
as C++ loops with OpenMP threads. It is compiled on first use with PyTorch's extension machinery
(``torch.utils.cpp_extension.load``, ninja) into torch's extension cache
(``$TORCH_EXTENSIONS_DIR``, default ``~/.cache/torch_extensions``), under a name that hashes the
source, the torch version and the CPU, so a later run (or another process) loads it in about a
second and a changed source or machine builds anew. Projection and SH colours stay torch ops
(O(N)); compositing, the O(pixels x pairs) part, is the compiled one.

Determinism: a tile is composited by one thread, and each Gaussian's gradient is summed from
its per-tile parts in a fixed order, so image and gradients are the same bit for bit at any
thread count (tested).
"""

from __future__ import annotations

import functools
import hashlib
import io
import os
import platform
import shutil
import sysconfig
from contextlib import redirect_stderr, redirect_stdout
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from .settings import RasterSettings

SOURCE = Path(__file__).parent / "csrc" / "composite_cpu.cpp"
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
    for part in (SOURCE.read_bytes(), torch.__version__.encode(), _cpu_signature().encode(), " ".join(CFLAGS).encode()):
        h.update(part)
    return f"exploregs_composite_cpu_{h.hexdigest()[:12]}"


def _toolchain_problem() -> str | None:
    compiler = os.environ.get("CXX", "c++")
    if shutil.which(compiler) is None:
        return f"no C++ compiler found (looked for '{compiler}'; install g++ or set CXX)"
    if shutil.which("ninja") is None:
        try:
            import ninja  # noqa: F401  (the PyPI package puts the binary next to python)
        except ImportError:
            return "ninja is not installed (pip install ninja)"
    include = sysconfig.get_paths().get("include")
    if not include or not (Path(include) / "Python.h").exists():
        return f"the Python headers are missing (no Python.h in {include}; install python3-dev)"
    return None


@functools.lru_cache(maxsize=1)
def _load() -> tuple[Any, str | None]:
    """(module, None) when the extension builds and loads, else (None, one-line reason)."""
    problem = _toolchain_problem()
    if problem is not None:
        return None, problem
    from torch.utils.cpp_extension import load

    log = io.StringIO()
    try:
        with redirect_stdout(log), redirect_stderr(log):
            module = load(name=extension_name(), sources=[str(SOURCE)], extra_cflags=CFLAGS,
                          extra_ldflags=LDFLAGS, verbose=False)  # fmt: skip
    except Exception as err:  # a failed build is reported as one line, never a traceback
        text = (str(err) + "\n" + log.getvalue()).strip().splitlines()
        # the compiler's first "error:" line says more than torch's "Error building extension"
        reason = next((ln.strip() for ln in text if "error:" in ln), text[0] if text else repr(err))
        return None, f"the C++ compositor did not build: {reason[:300]}"
    return module, None


def cpp_problem() -> str | None:
    """Why the compiled CPU backend cannot be used here (one line), or None (it is built and loaded)."""
    return _load()[1]


def extension() -> Any:
    module, problem = _load()
    if module is None:
        raise RuntimeError(problem)
    return module


def _thresholds(s: RasterSettings) -> tuple[float, float, float]:
    return s.alpha_max, s.alpha_min, s.transmittance_min


class CppBins:
    """Tile-Gaussian pairs made by the C++ binning (front to back within each tile)."""

    def __init__(self, means2d: Tensor, support: Tensor, depths: Tensor, width: int, height: int, tile_size: int):
        order = torch.argsort(depths, stable=True)  # pairs are made front to back
        m2, sup = means2d.detach().contiguous(), support.detach().to(means2d.dtype).contiguous()
        self.tile_offsets, self.pair_gauss, self.pair_slot, self.gauss_first, self.gauss_count = extension().bin_tiles(
            m2, sup, order.contiguous(), width, height, tile_size)
        self.width, self.height, self.tile_size = width, height, tile_size

    @property
    def n_pairs(self) -> int:
        return int(self.pair_gauss.numel())


class _CompositeCpp(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, opacities, feats, support, bins, settings, threads):  # type: ignore[override]
        tensors = [t.detach().contiguous() for t in (means2d, conics, opacities, feats)]
        sup = support.detach().to(means2d.dtype).contiguous()
        ext = extension()
        out, pair_stats = ext.composite_forward(
            *tensors, sup, bins.tile_offsets, bins.pair_gauss, bins.pair_slot, bins.width, bins.height,
            bins.tile_size, *_thresholds(settings), settings.visibility_stats, threads,
        )  # fmt: skip
        if settings.visibility_stats:
            visibility = ext.sum_pairs(pair_stats, bins.gauss_first, bins.gauss_count, threads)
        else:
            visibility = out.new_zeros(0, 2)
        ctx.mark_non_differentiable(visibility)
        ctx.save_for_backward(*tensors, sup, out)
        ctx.bins, ctx.settings, ctx.threads = bins, settings, threads
        return out, visibility

    @staticmethod
    def backward(ctx, grad_out, grad_visibility):  # type: ignore[override]
        means2d, conics, opacities, feats, sup, out = ctx.saved_tensors
        b, s = ctx.bins, ctx.settings
        ext = extension()
        pair_grad = ext.composite_backward(
            means2d, conics, opacities, feats, sup, b.tile_offsets, b.pair_gauss, b.pair_slot, out,
            grad_out.contiguous(), b.width, b.height, b.tile_size, *_thresholds(s), ctx.threads,
        )  # fmt: skip
        g = ext.sum_pairs(pair_grad, b.gauss_first, b.gauss_count, ctx.threads)
        return g[:, 0:2], g[:, 2:5], g[:, 5], g[:, 6:], None, None, None, None


def composite_cpp(
    means2d: Tensor, conics: Tensor, opacities: Tensor, feats: Tensor, support: Tensor, bins: CppBins,
    settings: RasterSettings, threads: int,
) -> tuple[Tensor, Tensor]:
    """Composites binned Gaussians: [H, W, F + 1] (features, then the accumulated alpha) and, with
    ``settings.visibility_stats``, [M, 2] per-Gaussian sums of w = alpha T and of alpha (else [0, 2])."""
    return _CompositeCpp.apply(means2d, conics, opacities, feats, support, bins, settings, threads)
