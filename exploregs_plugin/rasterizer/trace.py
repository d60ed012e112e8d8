"""Per-pixel trace: which Gaussians a pixel composites, in order, with their weights.

:func:`blend_pairs` and :func:`dcolor_dalpha` state the compositor's per-pixel rules on an
explicit [pixels, Gaussians] table (fine for diagnostics, far too large for rendering, which
``composite.py`` does in cache-sized chunks with the same rules)."""

from __future__ import annotations

import torch
from torch import Tensor

from ..cameras import Camera
from .projection import project_gaussians
from .rasterize import _validate
from .settings import RasterSettings
from .sh import sh_colors


def blend_pairs(power: Tensor, opacities: Tensor, in_box: Tensor, settings: RasterSettings):
    """Front-to-back blending of pixel-Gaussian pairs, one pixel a row, Gaussians in depth order.

    power: [P, M] exponent -0.5 d^T conic d; opacities: [M] or [P, M]; in_box: [P, M] bool (the
    pixel centre inside the support box). The rules of the compositor: alpha = min(alpha_max,
    o exp(power)), pairs with alpha < alpha_min (or outside the box) are skipped, and a pixel
    stops before the first Gaussian that would bring its transmittance below
    transmittance_min. Returns (raw [P, M] = o exp(power) before the clamp, alpha [P, M] (0 for
    pairs not composited), keep [P, M] bool, T_before [P, M], T_final [P, 1]).
    """
    raw = opacities * torch.exp(power.clamp_max(0.0))
    alpha = raw.clamp_max(settings.alpha_max)
    keep = in_box & (power <= 0) & (alpha >= settings.alpha_min)
    after = torch.cumprod(1.0 - alpha * keep, dim=1)
    keep = keep & (after >= settings.transmittance_min)  # T only decreases: a suffix is cut
    alpha = alpha * keep
    after = torch.cumprod(1.0 - alpha, dim=1)
    before = torch.cat([torch.ones_like(after[:, :1]), after[:, :-1]], dim=1)
    return raw, alpha, keep, before, after[:, -1:]


def dcolor_dalpha(alpha: Tensor, before: Tensor, t_final: Tensor, colors: Tensor, background: Tensor) -> Tensor:
    """dC/dalpha_m = T_{m-1} c_m - behind_m / (1 - alpha_m), where behind_m = sum_{i>m} w_i c_i
    + T_final bg is the colour composited behind m (w_i = alpha_i T_{i-1}).

    alpha, before: [P, M]; t_final: [P, 1]; colors: [P, M, C] (colour, or any linear function
    of it such as dL/dC . c); background: [P, C]. Returns [P, M, C].
    """
    w = (alpha * before)[..., None] * colors
    behind = w.sum(1, keepdim=True) - torch.cumsum(w, dim=1) + (t_final * background)[:, None, :]
    return before[..., None] * colors - behind / (1.0 - alpha)[..., None]


@torch.no_grad()
def trace_pixel(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    sh_coeffs: Tensor | None,
    camera: Camera,
    x: int,
    y: int,
    *,
    sh_degree: int | None = None,
    colors: Tensor | None = None,
    background: Tensor | None = None,
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
    viewmat, K, width, height = camera.viewmat, camera.K, camera.width, camera.height
    near_plane, far_plane = float(camera.near), float(camera.far)
    degree = _validate(
        means, quats, scales, opacities, sh_coeffs, colors, viewmat, K, width, height,
        sh_degree, None, None, background,
    )  # fmt: skip
    width, height = int(width), int(height)
    if not (0 <= x < width and 0 <= y < height):
        raise ValueError(f"trace_pixel: pixel ({x}, {y}) is outside the {width}x{height} image")
    dtype = means.dtype
    viewmat, K = viewmat.to(means), K.to(means)
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
    in_box = (dx.abs() <= proj.support[ids, 0]) & (dy.abs() <= proj.support[ids, 1])
    _, alpha, keep, before, t_final = blend_pairs(power[None], proj.opacities[ids][None], in_box[None], settings)
    kept = keep[0]
    ids, alpha, before, t_final = ids[kept], alpha[0, kept], before[0, kept], t_final[0, 0]
    if degree < 0:
        rgb = colors[ids].to(dtype)
    else:
        rgb = sh_colors(sh_coeffs[ids], means[ids], centre, degree)
    bg = torch.zeros(3, dtype=dtype, device=means.device) if background is None else background.to(means)
    w = (alpha * before)[:, None] * rgb
    dc_dalpha = dcolor_dalpha(alpha[None], before[None], t_final.reshape(1, 1), rgb[None], bg[None])[0]
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
