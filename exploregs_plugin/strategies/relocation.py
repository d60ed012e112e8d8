"""3DGS-MCMC relocation update (Kheradmand et al. 2024, eq. 9), as a pure function.

When a Gaussian (opacity o, scales s) is shared by n copies placed at the same centre, each copy
gets
    o' = 1 - (1 - o)^(1/n)
so that n copies blended at the centre give back 1 - (1 - o')^n = o, and
    s' = o * s / D,   D = sum_{i=1..n} sum_{k=0..i-1} C(i-1, k) (-1)^k o'^(k+1) / sqrt(k + 1),
which keeps the 1D integral of the blended opacity profile equal to the original one
(hockey-stick identity: D = sum_{j=1..n} C(n, j) (-1)^(j+1) o'^j / sqrt(j)).

The alternating sum cancels heavily for large n (C(50, 25) ~ 1e14), so it is evaluated in
float64 and cast back to the caller's dtype.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

N_MAX = 51
"""Largest number of copies the table covers (3DGS-MCMC uses 51)."""


def binomial_table(n_max: int = N_MAX) -> Tensor:
    """Binomial coefficients C(n, k) for 0 <= k <= n < n_max: [n_max, n_max] float64."""
    if n_max < 1:
        raise ValueError(f"n_max must be >= 1, got {n_max}")
    # one tensor from a list (1,326 element writes took 13 ms per strategy setup); every C(n, k)
    # with n < 51 is below 2^53, so exact in float64
    return torch.tensor([[float(math.comb(n, k)) for k in range(n_max)] for n in range(n_max)],
                        dtype=torch.float64)


def relocation_update(
    opacities: Tensor, scales: Tensor, ratios: Tensor, binoms: Tensor
) -> tuple[Tensor, Tensor]:
    """New opacity and scales for Gaussians shared by ``ratios`` copies each.

    opacities: [M] activated in [0, 1]; scales: [M, 3] activated; ratios: [M] integer copy
    counts (clamped to [1, n_max]); binoms: [n_max, n_max] from :func:`binomial_table`.
    Returns (new_opacities [M], new_scales [M, 3]) in the dtype of ``opacities``/``scales``.
    """
    if opacities.dim() != 1 or scales.shape != (opacities.shape[0], 3):
        raise ValueError(
            f"relocation_update: expected opacities [M] and scales [M, 3], got "
            f"{tuple(opacities.shape)} and {tuple(scales.shape)}"
        )
    n_max = binoms.shape[0]
    n = ratios.to(torch.long).clamp(1, n_max)
    o = opacities.to(torch.float64).clamp(0.0, 1.0)
    new_o = 1.0 - torch.pow(1.0 - o, 1.0 / n.to(torch.float64))

    # D = sum_{j=1..n} C(n, j) (-1)^(j+1) o'^j / sqrt(j); j runs to n_max so C(n, j) = 0 for
    # j > n masks the tail. C(n, j) for n = n_max needs one row past the (i-1) table.
    j = torch.arange(1, n_max + 1, dtype=torch.float64, device=o.device)  # [n_max]
    comb_n_j = _comb_rows(n, binoms.to(device=o.device, dtype=torch.float64))  # [M, n_max]
    signs = torch.where(j.to(torch.long) % 2 == 1, 1.0, -1.0).to(torch.float64)
    terms = comb_n_j * signs * torch.pow(new_o.unsqueeze(-1), j) / torch.sqrt(j)
    denom = terms.sum(dim=-1)
    # denom > 0 whenever o' > 0; a fully transparent source (o = 0) keeps its scale.
    safe = denom > 1e-300
    coeff = torch.where(safe, o / torch.where(safe, denom, torch.ones_like(denom)), 1.0)
    new_scales = scales.to(torch.float64) * coeff.unsqueeze(-1)
    return new_o.to(opacities.dtype), new_scales.to(scales.dtype)


def _comb_rows(n: Tensor, binoms: Tensor) -> Tensor:
    """C(n, j) for j = 1..n_max, per row: [M] -> [M, n_max], built from the (i-1, k) table.

    Pascal's rule C(n, j) = C(n-1, j-1) + C(n-1, j) needs only rows n-1 <= n_max-1 of the table.
    """
    prev = binoms[n - 1]  # [M, n_max]: C(n-1, k), k = 0..n_max-1
    shifted = torch.cat([prev[:, 1:], prev.new_zeros(prev.shape[0], 1)], dim=-1)  # C(n-1, j)
    return prev + shifted  # index j-1 holds C(n-1, j-1) + C(n-1, j) = C(n, j)
