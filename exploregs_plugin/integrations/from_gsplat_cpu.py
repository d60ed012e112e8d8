"""Torch stand-ins for the two CUDA-only helpers that gsplat 1.5.3's MCMC step calls, so that
``gsplat.strategy.MCMCStrategy`` runs on CPU tensors.

gsplat's ``relocate`` / ``sample_add`` call ``gsplat.relocation.compute_relocation`` and its
position noise calls ``gsplat.quat_scale_to_covar_preci``; both go straight to gsplat's compiled
CUDA extension (on a CPU-only machine the import of that extension fails). The stand-ins are our
own implementations of the same rules, one each in the project:

- relocation (3DGS-MCMC, Kheradmand et al. 2024, eq. 9): a Gaussian (o, s) shared by n copies
  gets o' = 1 - (1 - o)^(1/n) and s' = o s / D with
  D = sum_{i=1..n} sum_{k=0..i-1} C(i-1, k) (-1)^k o'^(k+1) / sqrt(k+1)
  -> ``exploregs_plugin.strategies.relocation.relocation_update`` (float64 sums, our own
  binomial table in float64: gsplat's table is float32, where C(50, 25) ~ 1.3e14 is not exact);
- covariance Sigma = R(q) diag(s)^2 R(q)^T (quaternion normalised first)
  -> ``exploregs_plugin.rasterizer.projection.covariances_3d``.

:func:`cpu_stand_ins` puts them into ``gsplat.strategy.ops`` only while gsplat's step runs on CPU
tensors and restores gsplat's own functions afterwards (also on error); on CUDA gsplat's kernels
run unchanged.
"""

from __future__ import annotations

import contextlib
import functools
import importlib
from collections.abc import Iterator

import torch
from torch import Tensor

from .patching import attribute_set_to

from ..rasterizer.projection import covariances_3d
from ..strategies.base import StrategyError
from ..strategies.relocation import binomial_table, relocation_update

STAND_INS = ("compute_relocation", "quat_scale_to_covar_preci")
"""Names in ``gsplat.strategy.ops`` that :func:`cpu_stand_ins` replaces on CPU tensors."""


@functools.lru_cache(maxsize=4)
def _exact_binomials(n_max: int) -> Tensor:
    # float64 holds every C(n, k) for n < 51 exactly (C(50, 25) < 2^53).
    return binomial_table(n_max)


def relocation_cpu(opacities: Tensor, scales: Tensor, ratios: Tensor, binoms: Tensor) -> tuple[Tensor, Tensor]:
    """``gsplat.relocation.compute_relocation`` for CPU tensors: (new opacities [N], new scales [N, 3]).

    Same arguments and the same clamp of ``ratios`` to [1, n_max] (n_max = rows of ``binoms``);
    only the size of gsplat's table is read, the coefficients come exact from
    :func:`binomial_table`. The formula is :func:`relocation_update`'s (module docstring)."""
    n_max = int(binoms.shape[0])
    return relocation_update(opacities.flatten(), scales, ratios.flatten(), _exact_binomials(n_max))


def covariance_cpu(
    quats: Tensor, scales: Tensor, compute_covar: bool = True, compute_preci: bool = True, triu: bool = False
) -> tuple[Tensor | None, Tensor | None]:
    """``gsplat.quat_scale_to_covar_preci`` for the one call gsplat's MCMC noise makes
    (full covariance [N, 3, 3], no precision): (R diag(s)^2 R^T, None)."""
    if compute_preci or triu or not compute_covar:
        raise StrategyError(
            "the CPU stand-in of gsplat's quat_scale_to_covar_preci gives only the full covariance "
            f"(asked: compute_covar={compute_covar}, compute_preci={compute_preci}, triu={triu})"
        )
    return covariances_3d(quats, scales), None


@contextlib.contextmanager
def cpu_stand_ins(device: torch.device) -> Iterator[None]:
    """Inside the block, gsplat's MCMC ops use :func:`relocation_cpu` and :func:`covariance_cpu`
    when ``device`` is the CPU; gsplat's own functions are back after it. Other devices: no change."""
    if torch.device(device).type != "cpu":
        yield
        return
    gsplat_ops = importlib.import_module("gsplat.strategy.ops")
    with contextlib.ExitStack() as stack:
        for name, stand_in in zip(STAND_INS, (relocation_cpu, covariance_cpu)):
            stack.enter_context(attribute_set_to(gsplat_ops, name, stand_in))
        yield
