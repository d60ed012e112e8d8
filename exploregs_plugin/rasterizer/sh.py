"""Real spherical harmonics up to degree 3, evaluated along unit view directions."""

from __future__ import annotations

import torch
from torch import Tensor

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)


def rgb_to_sh0(rgb: Tensor) -> Tensor:
    """SH DC coefficients whose colour is ``rgb`` (inverse of colour = SH_C0 * sh0 + 0.5, the
    3DGS convention). rgb: [N, 3] -> [N, 1, 3]."""
    return ((rgb - 0.5) / SH_C0).unsqueeze(1)


def sh_basis(dirs: Tensor, degree: int) -> Tensor:
    """SH basis values for unit directions.

    dirs: [N, 3] unit vectors; returns [N, (degree + 1)^2].
    """
    if not 0 <= degree <= 3:
        raise ValueError(f"sh degree must be in 0..3, got {degree}")
    x, y, z = dirs.unbind(-1)
    cols = [torch.full_like(x, SH_C0)]
    if degree >= 1:
        cols += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        cols += [
            SH_C2[0] * x * y,
            SH_C2[1] * y * z,
            SH_C2[2] * (2.0 * zz - xx - yy),
            SH_C2[3] * x * z,
            SH_C2[4] * (xx - yy),
        ]
    if degree >= 3:
        cols += [
            SH_C3[0] * y * (3.0 * xx - yy),
            SH_C3[1] * x * y * z,
            SH_C3[2] * y * (4.0 * zz - xx - yy),
            SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy),
            SH_C3[4] * x * (4.0 * zz - xx - yy),
            SH_C3[5] * z * (xx - yy),
            SH_C3[6] * x * (xx - 3.0 * yy),
        ]
    return torch.stack(cols, dim=-1)


def eval_sh(coeffs: Tensor, dirs: Tensor, degree: int) -> Tensor:
    """Raw SH value (no +0.5 offset, no clamp).

    coeffs: [N, K, 3] with K >= (degree + 1)^2; dirs: [N, 3] unit vectors; returns [N, 3].
    """
    n_basis = (degree + 1) ** 2
    if coeffs.shape[-2] < n_basis:
        raise ValueError(f"sh_coeffs has {coeffs.shape[-2]} coefficients, degree {degree} needs {n_basis}")
    basis = sh_basis(dirs, degree)  # [N, B]
    return torch.einsum("nb,nbc->nc", basis, coeffs[:, :n_basis, :])


def sh_colors(coeffs: Tensor, means_sh: Tensor, camera_center: Tensor, degree: int) -> Tensor:
    """3DGS colour max(SH(dir) + 0.5, 0) along the normalised camera-to-Gaussian direction.

    coeffs: [N, K, 3]; means_sh: [N, 3]; camera_center: [3]; returns [N, 3].
    """
    d = means_sh - camera_center
    # rsqrt of a clamped squared norm: a Gaussian sitting on the camera centre gets a finite
    # (arbitrary) direction instead of NaN.
    inv = torch.rsqrt((d * d).sum(-1, keepdim=True).clamp_min(1e-30))
    return (eval_sh(coeffs, d * inv, degree) + 0.5).clamp_min(0.0)
