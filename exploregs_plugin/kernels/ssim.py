"""SSIM map as one compiled kernel (forward and backward): the same image model as
:func:`exploregs_plugin.model.losses.ssim_map` (11 x 11 Gaussian window, sigma 1.5, zero padding),
without the five depthwise convolutions and their backward that dominate a CPU training step
after the renderer (docs/rasterizer.md)."""

from __future__ import annotations

import torch
from torch import Tensor

from .build import extension


class _SsimCpp(torch.autograd.Function):
    @staticmethod
    def forward(ctx, img, ref, c1, c2, threads):  # type: ignore[override]
        img, ref = img.detach().contiguous(), ref.detach().contiguous()
        ssim, moments = extension().ssim_forward(img, ref, c1, c2, threads)
        ctx.save_for_backward(img, ref, moments)
        ctx.constants = (c1, c2, threads)
        return ssim

    @staticmethod
    def backward(ctx, grad_map):  # type: ignore[override]
        img, ref, moments = ctx.saved_tensors
        c1, c2, threads = ctx.constants
        grad = extension().ssim_backward(img, ref, moments, grad_map.contiguous(), c1, c2, threads)
        return grad, None, None, None, None


def ssim_map_cpp(img: Tensor, ref: Tensor, c1: float, c2: float, threads: int) -> Tensor:
    """Per-pixel SSIM of [C, H, W] images (gradient for ``img`` only): [C, H, W]."""
    return _SsimCpp.apply(img, ref.detach(), c1, c2, threads)
