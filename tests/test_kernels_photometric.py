"""The fused training loss, (1 - lambda) L1 + lambda (1 - SSIM) in one kernel, against the torch
loss (L1 plus the convolution-based ssim_map): values, logged terms and gradients, the hard cases
(flat images, where the variances vanish; identical images, where |x - y| has no slope; images
smaller than the window; one channel), an upstream gradient other than 1 (a batch's mean), and the
same bits at any thread count."""

from __future__ import annotations

import os
import shutil

import pytest
import torch

from exploregs_plugin.kernels import cpp_problem
from exploregs_plugin.kernels.photometric import photometric_loss_cpp
from exploregs_plugin.model.losses import MSE_FLOOR, SSIM_C1, SSIM_C2, VIEW_PSNR, l1, photometric_loss, psnr, ssim

pytestmark = pytest.mark.skipif(shutil.which(os.environ.get("CXX", "c++")) is None, reason="no C++ compiler")


def _torch_loss(img: torch.Tensor, ref: torch.Tensor, lam: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    l1_term, dssim = l1(img, ref), 1.0 - ssim(img, ref)
    return (1.0 - lam) * l1_term + lam * dssim, l1_term, dssim


def _both(img: torch.Tensor, ref: torch.Tensor, lam: float = 0.2, threads: int = 2, upstream: float = 1.0):
    """((loss, l1, dssim), gradient) of the fused kernel, then of the torch loss."""
    out = []
    for loss_fn in (lambda x: photometric_loss_cpp(x, ref, lam, SSIM_C1, SSIM_C2, MSE_FLOOR, threads)[:3],
                    lambda x: _torch_loss(x, ref, lam)):
        x = img.clone().requires_grad_()
        loss, l1_term, dssim = loss_fn(x)
        (upstream * loss).backward()
        out.append((torch.stack([loss.detach(), l1_term.detach(), dssim.detach()]), x.grad))
    return out


@pytest.mark.parametrize("shape,lam", [((37, 53, 3), 0.2), ((5, 4, 3), 0.2), ((64, 11, 1), 0.2),
                                       ((23, 29, 3), 0.0), ((23, 29, 3), 1.0)])
def test_float64_values_and_gradients_match_the_torch_loss(shape, lam):
    assert cpp_problem() is None
    gen = torch.Generator().manual_seed(sum(shape))
    img = torch.rand(shape, generator=gen, dtype=torch.float64)
    ref = (img + 0.1 * torch.randn(shape, generator=gen, dtype=torch.float64)).clamp(0, 1)
    (v, g), (v_ref, g_ref) = _both(img, ref, lam)
    assert (v - v_ref).abs().max() <= 1e-13
    assert (g - g_ref).abs().max() <= 1e-13 * max(1.0, g_ref.abs().max().item())


def test_flat_identical_and_opposite_images():
    flat = torch.full((20, 24, 3), 0.5, dtype=torch.float64)
    (v, g), (v_ref, g_ref) = _both(flat, flat.clone())
    # identical: no error, SSIM 1, and sgn(0) = 0 as torch's abs, so no gradient at all
    assert torch.equal(v, torch.zeros(3, dtype=torch.float64))
    assert torch.isfinite(g).all() and g.abs().max() <= 1e-15 and (g - g_ref).abs().max() <= 1e-15
    black = torch.zeros(16, 16, 3, dtype=torch.float64)
    (v, g), (v_ref, g_ref) = _both(black, torch.ones_like(black))
    assert torch.isfinite(v).all() and torch.isfinite(g).all()
    assert (v - v_ref).abs().max() <= 1e-13 and (g - g_ref).abs().max() <= 1e-13
    assert v[1] == 1.0  # the L1 term of black against white


def test_float32_loss_and_gradient_close_to_the_torch_path():
    gen = torch.Generator().manual_seed(1)
    img = torch.rand(90, 120, 3, generator=gen)
    ref = torch.rand(90, 120, 3, generator=gen)
    (v, g), (v_ref, g_ref) = _both(img, ref)
    assert v.dtype == torch.float32 and (v - v_ref).abs().max() <= 1e-6
    assert (g - g_ref).abs().max() <= 1e-5 * g_ref.abs().max()
    # photometric_loss takes the kernel on the CPU and logs its two terms
    x = img.clone().requires_grad_()
    loss, terms = photometric_loss(x, ref, 0.2)
    assert loss.grad_fn is not None and not any(t.requires_grad for t in terms.values())
    assert torch.equal(torch.stack([loss.detach(), terms["l1"], terms["dssim"]]), v)
    # the view's PSNR from the same pass: float64 errors, the float64 PSNR's value to rounding
    assert terms[VIEW_PSNR].dtype == torch.float64 and abs(terms[VIEW_PSNR].item() - psnr(img, ref)) <= 1e-9


def test_the_psnr_of_identical_images_is_the_floors():
    img = torch.rand(12, 14, 3, generator=torch.Generator().manual_seed(6))
    view_psnr = photometric_loss_cpp(img, img.clone(), 0.2, SSIM_C1, SSIM_C2, MSE_FLOOR, 1)[3]
    assert view_psnr.item() == psnr(img, img.clone()) == 100.0


def test_an_upstream_gradient_scales_the_gradient():
    gen = torch.Generator().manual_seed(5)
    img, ref = torch.rand(30, 40, 3, generator=gen, dtype=torch.float64), torch.rand(30, 40, 3, generator=gen,
                                                                                       dtype=torch.float64)
    (_, g), (_, g_ref) = _both(img, ref, upstream=0.25)  # the mean of a batch of four views
    (_, g1), _ = _both(img, ref)
    assert (g - g_ref).abs().max() <= 1e-14 and torch.allclose(g, 0.25 * g1, rtol=1e-12, atol=0)


def test_same_bits_at_1_2_and_4_threads():
    gen = torch.Generator().manual_seed(2)
    img, ref = torch.rand(70, 90, 3, generator=gen), torch.rand(70, 90, 3, generator=gen)
    results = [_both(img, ref, threads=threads)[0] for threads in (1, 2, 4)]
    for v, g in results[1:]:
        assert torch.equal(v, results[0][0]) and torch.equal(g, results[0][1])
    psnrs = [photometric_loss_cpp(img, ref, 0.2, SSIM_C1, SSIM_C2, MSE_FLOOR, threads)[3] for threads in (1, 2, 4)]
    assert all(torch.equal(p, psnrs[0]) for p in psnrs)


def test_gradcheck():
    gen = torch.Generator().manual_seed(3)
    img = torch.rand(13, 15, 2, generator=gen, dtype=torch.float64, requires_grad=True)
    ref = torch.rand(13, 15, 2, generator=gen, dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda x: photometric_loss_cpp(x, ref, 0.2, SSIM_C1, SSIM_C2, MSE_FLOOR, 2)[0],
                                    [img])


def test_the_loss_benchmark_times_two_paths_that_agree():
    from exploregs_plugin.bench.components.loss import time_loss

    timing = time_loss(24, 32, threads=1, rounds=2, repeats=2)
    assert len(timing.compiled_ms) == len(timing.torch_ms) == 2
    assert all(t > 0 for t in timing.compiled_ms + timing.torch_ms)
    assert timing.loss_difference <= 1e-6


def test_images_of_two_shapes_are_one_clear_line():
    img = torch.rand(12, 14, 3)
    with pytest.raises(ValueError, match=r"photometric_loss: shapes differ: \(12, 14, 3\) vs \(12, 13, 3\)"):
        photometric_loss(img, torch.rand(12, 13, 3), 0.2)
