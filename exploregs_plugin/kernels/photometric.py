"""3DGS's training loss, (1 - lambda) L1 + lambda (1 - SSIM), as one compiled kernel (forward and
backward): the image model of :func:`exploregs_plugin.model.losses.photometric_loss` (SSIM with an
11 x 11 Gaussian window, sigma 1.5, zero padding), without the five depthwise convolutions that
dominated a CPU step after the renderer, and without the twenty-odd small operators of the L1
term, the means, the weighting and their backward (docs/training.md, "Operators per step")."""

from __future__ import annotations

import torch
from torch import Tensor

from .build import extension


class _PhotometricCpp(torch.autograd.Function):
    @staticmethod
    def forward(ctx, img, ref, ssim_lambda, c1, c2, mse_floor, threads):  # type: ignore[override]
        img, ref = img.detach().contiguous(), ref.detach().contiguous()
        loss, l1, dssim, psnr, moments = extension().photometric_forward(img, ref, ssim_lambda, c1, c2, mse_floor,
                                                                         threads)
        ctx.save_for_backward(moments)  # the five moments and both images as planes
        ctx.constants = (ssim_lambda, c1, c2, threads)
        ctx.mark_non_differentiable(l1, dssim, psnr)
        ctx.set_materialize_grads(False)  # no zero tensors for the logged values' gradients
        return loss, l1, dssim, psnr

    @staticmethod
    def backward(ctx, grad_loss, _grad_l1, _grad_dssim, _grad_psnr):  # type: ignore[override]
        if grad_loss is None:
            return None, None, None, None, None, None, None
        (moments,) = ctx.saved_tensors
        ssim_lambda, c1, c2, threads = ctx.constants
        grad = extension().photometric_backward(moments, grad_loss, ssim_lambda, c1, c2, threads)
        return grad, None, None, None, None, None, None


def photometric_loss_cpp(img: Tensor, ref: Tensor, ssim_lambda: float, c1: float, c2: float, mse_floor: float,
                         threads: int) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """(loss, mean |img - ref|, 1 - mean SSIM, PSNR in dB) of [H, W, C] images of one dtype, the
    loss with a gradient for ``img`` only, the PSNR -10 log10(max(MSE, mse_floor)) from float64
    errors (a float64 value; the training step logs it, and the same pass gives it for one more
    sum). The means are summed in float64 per image row and the rows added in order, so the values
    and the gradient are the same bits at any thread count."""
    return _PhotometricCpp.apply(img, ref.detach(), float(ssim_lambda), c1, c2, mse_floor, threads)
