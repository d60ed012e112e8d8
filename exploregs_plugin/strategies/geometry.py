"""Small pure functions on Gaussian attributes used by the strategies.

All functions work on any floating dtype (float32 in training, float64 in reference tests).
"""

from __future__ import annotations

import torch
from torch import Tensor

SH_C0 = 0.28209479177387814
"""Zeroth-order SH basis constant: colour = SH_C0 * sh0 + 0.5 (3DGS convention)."""

_EPS = 1e-12


def quat_to_rotmat(quats: Tensor) -> Tensor:
    """Rotation matrices of unnormalised wxyz quaternions.

    quats: [..., 4] -> [..., 3, 3]. A zero quaternion maps to the identity (the rasterizer's
    convention), so a degenerate row never produces NaN.
    """
    norm = quats.norm(dim=-1, keepdim=True)
    identity = torch.zeros_like(quats)
    identity[..., 0] = 1.0
    q = torch.where(norm > _EPS, quats / norm.clamp_min(_EPS), identity)
    w, x, y, z = q.unbind(-1)
    rows = (
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    )
    return torch.stack(rows, dim=-1).reshape(*quats.shape[:-1], 3, 3)


def covariance(quats: Tensor, scales: Tensor) -> Tensor:
    """World covariance Sigma = R S S^T R^T.

    quats: [N, 4] wxyz; scales: [N, 3] activated standard deviations -> [N, 3, 3].
    """
    rs = quat_to_rotmat(quats) * scales.unsqueeze(-2)  # R @ diag(s)
    return rs @ rs.transpose(-1, -2)


def random_unit_quats(n: int, generator: torch.Generator, dtype=torch.float32) -> Tensor:
    """Quaternions uniform on the unit 3-sphere (normalised 4D Gaussian samples): [n, 4]."""
    q = torch.randn(n, 4, generator=generator, dtype=dtype)
    norm = q.norm(dim=-1, keepdim=True)
    # A 4D standard normal sample has norm 0 with probability 0; keep the guard anyway.
    fallback = torch.zeros_like(q)
    fallback[:, 0] = 1.0
    return torch.where(norm > _EPS, q / norm.clamp_min(_EPS), fallback)


def rgb_to_sh0(rgb: Tensor) -> Tensor:
    """SH DC coefficients whose colour is ``rgb``: [N, 3] -> [N, 1, 3]."""
    return ((rgb - 0.5) / SH_C0).unsqueeze(1)


def max_world_scale(log_scales: Tensor) -> Tensor:
    """Largest activated scale per Gaussian, the 3DGS 'world size': [N, 3] -> [N]."""
    if log_scales.shape[0] == 0:
        return log_scales.new_zeros(0)
    return torch.exp(log_scales).max(dim=-1).values
