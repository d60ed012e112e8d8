"""Small pure functions on Gaussian attributes used by the strategies (rotations, covariances
and SH colours come from the rasterizer, which defines them).

All functions work on any floating dtype (float32 in training, float64 in reference tests).
"""

from __future__ import annotations

import torch
from torch import Tensor

_EPS = 1e-12


def random_unit_quats(n: int, generator: torch.Generator, dtype=torch.float32) -> Tensor:
    """Quaternions uniform on the unit 3-sphere (normalised 4D Gaussian samples): [n, 4]."""
    q = torch.randn(n, 4, generator=generator, dtype=dtype, device=generator.device)
    norm = q.norm(dim=-1, keepdim=True)
    # A 4D standard normal sample has norm 0 with probability 0; keep the guard anyway.
    fallback = torch.zeros_like(q)
    fallback[:, 0] = 1.0
    return torch.where(norm > _EPS, q / norm.clamp_min(_EPS), fallback)


def max_world_scale(log_scales: Tensor) -> Tensor:
    """Largest activated scale per Gaussian, the 3DGS 'world size': [N, 3] -> [N]."""
    if log_scales.shape[0] == 0:
        return log_scales.new_zeros(0)
    return torch.exp(log_scales).max(dim=-1).values
