"""Per-pixel trace: which Gaussians a pixel composites, in order, with their weights."""

from __future__ import annotations

import torch
from torch import Tensor

from .projection import project_gaussians
from .rasterize import _validate
from .settings import RasterSettings
from .sh import sh_colors


@torch.no_grad()
def trace_pixel(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    sh_coeffs: Tensor | None,
    viewmat: Tensor,
    K: Tensor,
    width: int,
    height: int,
    x: int,
    y: int,
    *,
    sh_degree: int | None = None,
    colors: Tensor | None = None,
    background: Tensor | None = None,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    settings: RasterSettings | None = None,
) -> dict[str, Tensor]:
    """Traces pixel column ``x``, row ``y`` (its centre is at (x + 0.5, y + 0.5)).

    Arguments as for :func:`rasterize`. Returns, for the m Gaussians composited front to back:
    "ids" [m] int64 (rows of the input), "depths" [m], "alphas" [m], "T_before" [m]
    (transmittance in front of each), "colors" [m, 3], "dC_dalpha" [m, 3] =
    T_before_m (c_m - C_behind_m), where C_behind_m is the colour composited behind m (background
    included) normalised by the transmittance after m; plus "color" [3] (the pixel) and
    "T_final" [] (transmittance after the last).
    """
    settings = settings or RasterSettings()
    degree = _validate(
        means, quats, scales, opacities, sh_coeffs, colors, viewmat, K, width, height,
        sh_degree, None, None, background,
    )  # fmt: skip
    width, height = int(width), int(height)
    if not (0 <= x < width and 0 <= y < height):
        raise ValueError(f"trace_pixel: pixel ({x}, {y}) is outside the {width}x{height} image")
    dtype = means.dtype
    viewmat, K = viewmat.to(dtype), K.to(dtype)
    proj = project_gaussians(
        means, quats, scales, opacities, viewmat, K, width, height, near_plane, far_plane, settings
    )
    centre = -(viewmat[:3, :3].T @ viewmat[:3, 3])
    ids = torch.nonzero(proj.visible).squeeze(1)
    ids = ids[torch.argsort(proj.depths[ids], stable=True)]
    dx = x + 0.5 - proj.means2d[ids, 0]
    dy = y + 0.5 - proj.means2d[ids, 1]
    a, b, c = proj.conics[ids].unbind(-1)
    power = -0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy
    alpha = (proj.opacities[ids] * torch.exp(power)).clamp_max(settings.alpha_max)
    in_box = (dx.abs() <= proj.support[ids, 0]) & (dy.abs() <= proj.support[ids, 1])
    keep = in_box & (power <= 0) & (alpha >= settings.alpha_min)
    ids, alpha = ids[keep], alpha[keep]
    after = torch.cumprod(1.0 - alpha, 0)
    n = int((after >= settings.transmittance_min).sum())  # stopping is a suffix: T only decreases
    ids, alpha, after = ids[:n], alpha[:n], after[:n]
    before = torch.cat([after.new_ones(1), after[:-1]])
    if degree < 0:
        rgb = colors[ids].to(dtype)
    else:
        rgb = sh_colors(sh_coeffs[ids], means[ids], centre, degree)
    bg = torch.zeros(3, dtype=dtype) if background is None else background.to(dtype)
    t_final = after[-1] if n > 0 else torch.ones((), dtype=dtype)
    w = (alpha * before)[:, None] * rgb
    # colour behind m: sum_{i>m} w_i c_i + T_final bg, as seen through T after m
    behind = torch.flip(torch.cumsum(torch.flip(w, [0]), 0), [0]) - w + t_final * bg
    dc_dalpha = before[:, None] * rgb - behind / (1.0 - alpha)[:, None]
    return {
        "ids": ids,
        "depths": proj.depths[ids],
        "alphas": alpha,
        "T_before": before,
        "colors": rgb,
        "dC_dalpha": dc_dalpha,
        "color": w.sum(0) + t_final * bg,
        "T_final": t_final,
    }
