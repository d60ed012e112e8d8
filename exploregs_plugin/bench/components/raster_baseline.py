"""A plain chunked compositor on autograd: the yardstick the benchmark compares against.

Same projection, SH and tile binning as :func:`rasterize`, and the same image model; the
compositing is written directly in torch ops per chunk of tiles and differentiated by autograd,
which keeps every per-chunk intermediate alive until backward.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from exploregs_plugin.cameras import Camera
from exploregs_plugin.rasterizer.projection import project_gaussians
from exploregs_plugin.rasterizer.settings import RasterSettings
from exploregs_plugin.rasterizer.sh import sh_colors
from exploregs_plugin.rasterizer.tiling import bin_gaussians, gather_table, plan_chunks


def rasterize_baseline(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    sh_coeffs: Tensor,
    camera: Camera,
    *,
    background: Tensor | None = None,
    settings: RasterSettings | None = None,
) -> tuple[Tensor, Tensor]:
    """image [H, W, 3] and alpha [H, W, 1] (full SH degree), with the arguments of ``rasterize``."""
    s = settings or RasterSettings()
    dtype = means.dtype
    viewmat, K, width, height = camera.viewmat, camera.K, camera.width, camera.height
    proj = project_gaussians(means, quats, scales, opacities, viewmat, K, width, height, camera.near, camera.far, s)
    vis = torch.nonzero(proj.visible).squeeze(1)
    degree = math.isqrt(sh_coeffs.shape[1]) - 1
    centre = -(viewmat[:3, :3].T @ viewmat[:3, 3])
    rgb = sh_colors(sh_coeffs[vis], means[vis], centre, degree)
    m2d, con, op, sup = proj.means2d[vis], proj.conics[vis], proj.opacities[vis], proj.support[vis]
    bins = bin_gaussians(m2d.detach(), sup, proj.depths.detach()[vis], width, height, s.tile_size)
    ts = s.tile_size
    pix = torch.arange(ts, dtype=dtype) + 0.5
    out = torch.zeros(bins.n_tiles, ts * ts, 4, dtype=dtype)
    pieces, where = [], []
    for tiles, k in plan_chunks(bins, s.chunk_elements):
        idx = gather_table(bins, tiles, k, 0)
        valid = torch.arange(k)[None, :] < bins.tile_counts[tiles][:, None]  # [B, K]
        px = (tiles % bins.tiles_x).to(dtype)[:, None, None] * ts + pix[None, None, :]  # [B, 1, S]
        py = (tiles // bins.tiles_x).to(dtype)[:, None, None] * ts + pix[None, :, None]  # [B, S, 1]
        px = px.expand(-1, ts, -1).reshape(len(tiles), -1, 1)  # [B, P, 1]
        py = py.expand(-1, -1, ts).reshape(len(tiles), -1, 1)
        dx = px - m2d[idx][:, None, :, 0]  # [B, P, K]
        dy = py - m2d[idx][:, None, :, 1]
        a, b, c = (con[idx][:, None, :, i] for i in range(3))
        power = -0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy
        alpha = torch.clamp_max(op[idx][:, None, :] * torch.exp(power), s.alpha_max)
        box = (dx.abs() <= sup[idx][:, None, :, 0]) & (dy.abs() <= sup[idx][:, None, :, 1])
        use = box & valid[:, None, :] & (power <= 0) & (alpha >= s.alpha_min)
        alpha = torch.where(use, alpha, torch.zeros_like(alpha))
        t_after = torch.cumprod(1 - alpha, -1)
        t_before = torch.cat([torch.ones_like(t_after[..., :1]), t_after[..., :-1]], -1)
        w = torch.where(t_after >= s.transmittance_min, alpha * t_before, torch.zeros_like(alpha))
        col = torch.einsum("bpk,bkc->bpc", w, rgb[idx])
        pieces.append(torch.cat([col, w.sum(-1, keepdim=True)], -1))
        where.append(tiles)
    if pieces:
        out = out.index_put((torch.cat(where),), torch.cat(pieces))
    img = out.view(bins.tiles_y, bins.tiles_x, ts, ts, 4).permute(0, 2, 1, 3, 4)
    img = img.reshape(bins.tiles_y * ts, bins.tiles_x * ts, 4)[:height, :width]
    image, acc = img[..., :3], img[..., 3:]
    if background is not None:
        image = image + (1 - acc) * background
    return image, acc
