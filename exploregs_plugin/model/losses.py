"""Image losses and metrics (pure functions). Images are [H, W, 3] floats in [0, 1]."""

from __future__ import annotations

import math
from typing import Literal

import torch
import torch.nn.functional as F
from torch import Tensor

SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
# Stabilisers of Wang et al. (2004) for a dynamic range of 1: C1 = (0.01 L)^2, C2 = (0.03 L)^2.
SSIM_C1 = 0.01**2
SSIM_C2 = 0.03**2
MSE_FLOOR = 1e-10  # PSNR of a perfect match is 100 dB instead of inf


def _gaussian_kernel_1d(size: int, sigma: float, dtype: torch.dtype, device: torch.device) -> Tensor:
    coords = torch.arange(size, dtype=dtype, device=device) - (size - 1) / 2.0
    g = torch.exp(-(coords**2) / (2.0 * sigma**2))
    return g / g.sum()


def ssim_map(img: Tensor, ref: Tensor) -> Tensor:
    """Per-pixel SSIM with an 11x11 Gaussian window (sigma 1.5), zero padding as in 3DGS.

    img, ref: [H, W, C]. Returns [H, W, C]. The window is separable (an outer product of 1D
    Gaussians), so the five local moments are filtered by one 1x11 and one 11x1 pass over the
    stacked maps: 22 taps per pixel instead of 121, in two convolution calls instead of five.
    """
    if img.shape != ref.shape:
        raise ValueError(f"ssim: shapes differ: {tuple(img.shape)} vs {tuple(ref.shape)}")
    channels = img.shape[-1]
    x = img.permute(2, 0, 1)
    y = ref.permute(2, 0, 1)
    maps = torch.cat([x, y, x * x, y * y, x * y], dim=0).unsqueeze(0)  # [1, 5C, H, W]
    g = _gaussian_kernel_1d(SSIM_WINDOW, SSIM_SIGMA, img.dtype, img.device)
    n = maps.shape[1]
    pad = SSIM_WINDOW // 2
    blurred = F.conv2d(maps, g.view(1, 1, 1, -1).expand(n, 1, 1, -1), padding=(0, pad), groups=n)
    blurred = F.conv2d(blurred, g.view(1, 1, -1, 1).expand(n, 1, -1, 1), padding=(pad, 0), groups=n)
    mu_x, mu_y, e_xx, e_yy, e_xy = blurred.squeeze(0).split(channels, dim=0)
    sigma_xx = e_xx - mu_x * mu_x
    sigma_yy = e_yy - mu_y * mu_y
    sigma_xy = e_xy - mu_x * mu_y
    num = (2 * mu_x * mu_y + SSIM_C1) * (2 * sigma_xy + SSIM_C2)
    den = (mu_x * mu_x + mu_y * mu_y + SSIM_C1) * (sigma_xx + sigma_yy + SSIM_C2)
    return (num / den).permute(1, 2, 0)


def ssim(img: Tensor, ref: Tensor) -> Tensor:
    """Mean SSIM of two [H, W, C] images (scalar)."""
    return ssim_map(img, ref).mean()


def l1(img: Tensor, ref: Tensor) -> Tensor:
    return (img - ref).abs().mean()


def psnr(img: Tensor, ref: Tensor, mask: Tensor | None = None) -> float:
    """PSNR in dB for images in [0, 1]; ``mask`` [H, W] bool restricts it to a region.

    Returns NaN for an empty mask (the region does not appear in this image).
    """
    err = (img.detach().double() - ref.detach().double()) ** 2
    if mask is not None:
        if mask.shape != img.shape[:2]:
            raise ValueError(f"psnr: mask shape {tuple(mask.shape)} != image {tuple(img.shape[:2])}")
        if not bool(mask.any()):
            return float("nan")
        err = err[mask]
    mse = max(float(err.mean()), MSE_FLOOR)
    return -10.0 * math.log10(mse)


def photometric_loss(img: Tensor, ref: Tensor, ssim_lambda: float) -> tuple[Tensor, dict[str, Tensor]]:
    """3DGS loss: (1 - lambda) L1 + lambda (1 - SSIM). Returns (loss, terms)."""
    l1_term = l1(img, ref)
    ssim_term = 1.0 - ssim(img, ref)
    loss = (1.0 - ssim_lambda) * l1_term + ssim_lambda * ssim_term
    return loss, {"l1": l1_term.detach(), "dssim": ssim_term.detach()}


DepthSpace = Literal["depth", "inverse"]


def depth_l1(depth: Tensor, target: Tensor, space: DepthSpace = "depth") -> Tensor:
    """Mean L1 between rendered and target depth over pixels where both are usable.

    depth: [H, W, 1] rendered expected depth (0 where nothing was rendered); target: [H, W, 1]
    (<= 0 or non-finite: no depth). ``space`` 'depth' compares z; 'inverse' compares 1/z, so an
    error at depth z weighs about 1/z^2 as much and far pixels do not dominate. In inverse space
    pixels with no rendered depth are left out (1/0 has no meaning there). Returns a scalar (0,
    still attached to ``depth``, when no pixel is usable).
    """
    valid = torch.isfinite(target) & (target > 0)
    if space == "depth":
        diff = depth - target
    elif space == "inverse":
        valid = valid & (depth > 0)
        diff = 1.0 / depth.clamp_min(1e-12) - 1.0 / target.clamp_min(1e-12)
    else:
        raise ValueError(f"depth loss space must be 'depth' or 'inverse', got {space!r}")
    return diff.abs()[valid].mean() if bool(valid.any()) else depth.sum() * 0.0
