"""The compiled CPU compositor (``RasterSettings.backend = "cpp"``): building it, and its autograd Function.

``csrc/project_cpu.cpp`` holds the EWA projection, ``csrc/sh_cpu.cpp`` the SH colours and
``csrc/composite_cpu.cpp`` tile binning and front-to-back compositing, each forward and backward,
as C++ loops with OpenMP threads. It is compiled on first use with PyTorch's extension machinery
(``torch.utils.cpp_extension.load``, ninja) into torch's extension cache
(``$TORCH_EXTENSIONS_DIR``, default ``~/.cache/torch_extensions``), under a name that hashes the
source, the torch version and the CPU, so a later run (or another process) loads it in about a
second and a changed source or machine builds anew. Projection and SH colours fall back to the
torch ops when the branch ablation feeds separate tensors to their paths, or the camera itself
needs a gradient.

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
import sys
import sysconfig
from contextlib import redirect_stderr, redirect_stdout
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from .projection import Projected
from .settings import RasterSettings

SOURCES = [Path(__file__).parent / "csrc" / name for name in ("composite_cpu.cpp", "project_cpu.cpp", "sh_cpu.cpp")]
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
    for part in (*(p.read_bytes() for p in SOURCES), torch.__version__.encode(), _cpu_signature().encode(),
                 " ".join(CFLAGS).encode()):
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


def _built(name: str) -> bool:
    """Whether torch's extension cache already holds a build of ``name`` (then loading takes about a second)."""
    from torch.utils.cpp_extension import _get_build_directory

    try:
        return (Path(_get_build_directory(name, verbose=False)) / f"{name}.so").exists()
    except Exception:  # a private helper of torch's: if it changes, only the progress line is lost
        return True


@functools.lru_cache(maxsize=1)
def _load() -> tuple[Any, str | None]:
    """(module, None) when the extension builds and loads, else (None, one-line reason)."""
    problem = _toolchain_problem()
    if problem is not None:
        return None, problem
    from torch.utils.cpp_extension import load

    name = extension_name()
    if not _built(name):
        print("building the compiled CPU renderer (once per machine and version; about a minute)...", file=sys.stderr,
              flush=True)
    log = io.StringIO()
    try:
        with redirect_stdout(log), redirect_stderr(log):
            module = load(name=name, sources=[str(p) for p in SOURCES], extra_cflags=CFLAGS,
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


class _ProjectCpp(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, quats, scales, opacities, viewmat, K, width, height, near, far, settings, threads):  # type: ignore[override]
        inputs = [t.detach().contiguous() for t in (means, quats, scales, opacities)]
        camera = (viewmat.detach(), K.detach(), width, height, float(near), float(far), settings.eps2d,
                  settings.sigma_radius, settings.guard_band, settings.antialiased)  # fmt: skip
        means2d, conics, opac, depths, radii, support, visible = extension().project_forward(*inputs, *camera, threads)
        ctx.mark_non_differentiable(radii, support, visible)
        ctx.save_for_backward(*inputs)
        ctx.camera, ctx.threads = camera, threads
        return means2d, conics, opac, depths, radii, support, visible

    @staticmethod
    def backward(ctx, g_means2d, g_conics, g_opac, g_depths, *_):  # type: ignore[override]
        inputs = ctx.saved_tensors
        n, like = inputs[0].shape[0], inputs[0]
        grads = [like.new_zeros(shape) if g is None else g.contiguous()
                 for g, shape in ((g_means2d, (n, 2)), (g_conics, (n, 3)), (g_opac, (n,)), (g_depths, (n,)))]
        d = extension().project_backward(*inputs, *ctx.camera, *grads, ctx.threads)
        return (*d, None, None, None, None, None, None, None, None)


def project_cpp(
    means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, viewmat: Tensor, K: Tensor, width: int,
    height: int, near_plane: float, far_plane: float, settings: RasterSettings, threads: int,
) -> Projected:
    """:func:`projection.project_gaussians` as one compiled kernel (forward and backward), for one
    tensor of means (no separate covariance path) and a camera without gradient."""
    means2d, conics, opac, depths, radii, support, visible = _ProjectCpp.apply(
        means, quats, scales, opacities, viewmat, K, width, height, near_plane, far_plane, settings, threads)
    return Projected(means2d, conics, opac, depths, radii, support, visible)


class _ShCpp(torch.autograd.Function):
    @staticmethod
    def forward(ctx, coeffs, means, rows, camera_center, degree, threads):  # type: ignore[override]
        inputs = (coeffs.detach().contiguous(), means.detach().contiguous(), rows.contiguous(), camera_center.detach())
        ctx.save_for_backward(*inputs)
        ctx.degree, ctx.threads = degree, threads
        return extension().sh_forward(*inputs, degree, threads)

    @staticmethod
    def backward(ctx, g_colors):  # type: ignore[override]
        d_coeffs, d_means = extension().sh_backward(*ctx.saved_tensors, ctx.degree, g_colors.contiguous(), ctx.threads)
        return d_coeffs, d_means, None, None, None, None


def sh_colors_cpp(coeffs: Tensor, means: Tensor, rows: Tensor, camera_center: Tensor, degree: int,
                  threads: int) -> Tensor:
    """:func:`sh.sh_colors` of the rows ``rows`` [M] of coeffs [N, K, 3] and means [N, 3]: [M, 3]."""
    return _ShCpp.apply(coeffs, means, rows, camera_center, degree, threads)
