"""Image losses and metrics (pure functions). Images are [H, W, 3] floats in [0, 1]."""

from __future__ import annotations

import math
from typing import Literal, Sequence

import torch
import torch.nn.functional as F
from torch import Tensor

from exploregs_plugin.kernels import cpp_problem
from exploregs_plugin.kernels.photometric import photometric_loss_cpp
from exploregs_plugin.rasterizer.composite import thread_budget

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
    mu_x, mu_y, sigma_xx, sigma_yy, sigma_xy = _local_moments(img.permute(2, 0, 1), ref.permute(2, 0, 1),
                                                              SSIM_WINDOW // 2)
    num = (2 * mu_x * mu_y + SSIM_C1) * (2 * sigma_xy + SSIM_C2)
    den = (mu_x * mu_x + mu_y * mu_y + SSIM_C1) * (sigma_xx + sigma_yy + SSIM_C2)
    return (num / den).permute(1, 2, 0)


def _local_moments(x: Tensor, y: Tensor, pad: int) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Gaussian-window means, variances and covariance of x, y [C, H, W] (zero padding ``pad``;
    0: only windows inside the image, [C, H - 10, W - 10])."""
    channels = x.shape[0]
    maps = torch.cat([x, y, x * x, y * y, x * y], dim=0).unsqueeze(0)  # [1, 5C, H, W]
    g = _gaussian_kernel_1d(SSIM_WINDOW, SSIM_SIGMA, x.dtype, x.device)
    n = maps.shape[1]
    blurred = F.conv2d(maps, g.view(1, 1, 1, -1).expand(n, 1, 1, -1), padding=(0, pad), groups=n)
    blurred = F.conv2d(blurred, g.view(1, 1, -1, 1).expand(n, 1, -1, 1), padding=(pad, 0), groups=n)
    mu_x, mu_y, e_xx, e_yy, e_xy = blurred.squeeze(0).split(channels, dim=0)
    return mu_x, mu_y, e_xx - mu_x * mu_x, e_yy - mu_y * mu_y, e_xy - mu_x * mu_y


MS_SSIM_WEIGHTS = (0.0448, 0.2856, 0.3001, 0.2363, 0.1333)
"""Exponents of the five scales of MS-SSIM (Wang, Simoncelli and Bovik 2003)."""


def ms_ssim_levels(height: int, width: int) -> int:
    """Scales of MS-SSIM for an image: five, or as many as keep the coarsest scale at least one
    window (11 px) wide; at least one (plain SSIM of the valid windows)."""
    levels = 1
    while levels < len(MS_SSIM_WEIGHTS) and min(height, width) // 2 ** levels >= SSIM_WINDOW:
        levels += 1
    return levels


def ms_ssim(img: Tensor, ref: Tensor, mask: Tensor | None = None) -> float:
    """Multi-scale SSIM of [H, W, C] images in [0, 1], with windows inside the image (as the
    reference implementation):

        MS-SSIM = SSIM_M^{w_M} prod_{j < M} cs_j^{w_j}

    per channel, then averaged over the channels, where cs_j is the mean contrast-structure term
    at scale j (2x2 average pooling between scales) and SSIM_M the mean SSIM at the coarsest. An
    image too small for five scales uses fewer (:func:`ms_ssim_levels`) with the first weights
    renormalised to sum to 1. Negative means are clamped to 0 (as common implementations do) so
    that the powers stay real.

    ``mask`` [H, W] bool restricts it to a region: each scale's means are weighted by the share
    of each window centre that lies in the region (the mask average-pooled like the images). A
    region that no window centre of a coarse scale touches (a thin band along the border) is
    scored on the finer scales it has; NaN when it has none."""
    return ms_ssim_many(img, ref, [mask])[0]


def ms_ssim_many(img: Tensor, ref: Tensor, masks: Sequence[Tensor | None]) -> list[float]:
    """:func:`ms_ssim` for several masks (None: the whole image) from one pass over the scales:
    the local moments are computed once and pooled per mask."""
    if img.shape != ref.shape:
        raise ValueError(f"ms_ssim: shapes differ: {tuple(img.shape)} vs {tuple(ref.shape)}")
    height, width = img.shape[:2]
    if min(height, width) < SSIM_WINDOW:
        raise ValueError(f"ms_ssim needs images of at least {SSIM_WINDOW} px a side, got {width}x{height}")
    x = img.detach().double().permute(2, 0, 1)
    y = ref.detach().double().permute(2, 0, 1)
    regions = [None if m is None else m.to(x.device, torch.float64)[None] for m in masks]
    crop = SSIM_WINDOW // 2
    cs_means: list[list[Tensor]] = [[] for _ in masks]  # per mask, per level: [C]
    ssim_means: list[list[Tensor]] = [[] for _ in masks]
    open_masks = set(range(len(masks)))  # masks that still have a window centre at this scale
    for level in range(ms_ssim_levels(height, width)):
        if level:
            x, y = F.avg_pool2d(x[None], 2)[0], F.avg_pool2d(y[None], 2)[0]
            regions = [None if r is None else F.avg_pool2d(r[None], 2)[0] for r in regions]
        weights: dict[int, Tensor | None] = {}
        for k in sorted(open_masks):
            region = regions[k]
            weight = None if region is None else region[:, crop:region.shape[1] - crop, crop:region.shape[2] - crop]
            if weight is not None and float(weight.sum()) <= 0.0:
                open_masks.discard(k)  # scored on the finer scales only
                continue
            weights[k] = weight
        if not weights:
            break
        mu_x, mu_y, sigma_xx, sigma_yy, sigma_xy = _local_moments(x, y, 0)
        cs = (2 * sigma_xy + SSIM_C2) / (sigma_xx + sigma_yy + SSIM_C2)
        full = (2 * mu_x * mu_y + SSIM_C1) / (mu_x * mu_x + mu_y * mu_y + SSIM_C1) * cs
        for k, weight in weights.items():
            for term, means in ((cs, cs_means[k]), (full, ssim_means[k])):
                mean = term.mean(dim=(1, 2)) if weight is None else (term * weight).sum(dim=(1, 2)) / weight.sum()
                means.append(mean.clamp_min(0.0))
    return [_combine_scales(cs, full) for cs, full in zip(cs_means, ssim_means)]


def _combine_scales(cs_means: list[Tensor], ssim_means: list[Tensor]) -> float:
    """SSIM_M^{w_M} prod_{j < M} cs_j^{w_j} over the scales measured, averaged over channels."""
    if not cs_means:
        return float("nan")
    weights = [w / sum(MS_SSIM_WEIGHTS[:len(cs_means)]) for w in MS_SSIM_WEIGHTS[:len(cs_means)]]
    value = ssim_means[-1] ** weights[-1]
    for cs_mean, w in zip(cs_means[:-1], weights[:-1]):
        value = value * cs_mean ** w
    return float(value.mean())


def d_ssim(ms_ssim_value: float) -> float:
    """Structural dissimilarity as the dynamic-scene papers report it (4DGS, Neu3D): (1 - MS-SSIM) / 2."""
    return (1.0 - ms_ssim_value) / 2.0


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


def psnr_on_device(img: Tensor, ref: Tensor) -> Tensor:
    """PSNR in dB as a 0-dim float64 tensor on the images' device, without reading the device
    (a training step's, read only where it is logged). The same squared error and floor as
    :func:`psnr`, but torch's log10, which may differ from the host's in the last bit (the
    training step rounds it to float32, as it always did): evaluations keep :func:`psnr`."""
    err = (img.detach().double() - ref.detach().double()) ** 2
    return -10.0 * torch.log10(err.mean().clamp_min(MSE_FLOOR))


def pooled_psnr(squared_error: float, count: int) -> float:
    """PSNR of pixels pooled over several images, -10 log10(max(sum of squared error / count,
    MSE_FLOOR)), from their summed per-pixel squared error; NaN for no pixels (a region that no
    test image shows)."""
    if count <= 0:
        return float("nan")
    return -10.0 * math.log10(max(squared_error / count, MSE_FLOOR))


VIEW_PSNR = "psnr"
"""The logged part of :func:`photometric_loss` that is the view's PSNR (where the compiled kernel
computed it in the loss's pass; a caller that logs the PSNR computes it itself when it is absent)."""


def photometric_loss(img: Tensor, ref: Tensor, ssim_lambda: float) -> tuple[Tensor, dict[str, Tensor]]:
    """3DGS loss: (1 - lambda) L1 + lambda (1 - SSIM). Returns (loss, terms): ``l1``, ``dssim``.

    On the CPU, where the compiled kernels build, the whole loss is one kernel forward and one
    backward (the same values as the torch path below up to float rounding, tested): the torch
    path is about twenty operators more per step, and its five depthwise convolutions cost a
    fraction of a step that the kernel does not. The kernel's terms also hold the view's PSNR
    (:data:`VIEW_PSNR`, float64, as :func:`psnr_on_device` up to the order of its sum)."""
    if img.shape != ref.shape:  # before the kernel, whose own check is a C++ error, not this line
        raise ValueError(f"photometric_loss: shapes differ: {tuple(img.shape)} vs {tuple(ref.shape)}")
    if img.device.type == "cpu" and img.dtype in (torch.float32, torch.float64) and cpp_problem() is None:
        loss, l1_term, ssim_term, view_psnr = photometric_loss_cpp(img, ref.to(img.dtype), ssim_lambda, SSIM_C1,
                                                                   SSIM_C2, MSE_FLOOR, thread_budget())
        return loss, {"l1": l1_term, "dssim": ssim_term, VIEW_PSNR: view_psnr}
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
