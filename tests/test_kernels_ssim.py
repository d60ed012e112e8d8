"""The fused SSIM kernel against the convolution-based ssim_map: values and gradients, the hard
cases of SSIM (flat images, where the variances vanish; images smaller than the window), and the
same bits at any thread count."""

from __future__ import annotations

import os
import shutil

import pytest
import torch

from exploregs_plugin.kernels import cpp_problem
from exploregs_plugin.kernels.ssim import ssim_map_cpp
from exploregs_plugin.model.losses import SSIM_C1, SSIM_C2, ssim, ssim_map

pytestmark = pytest.mark.skipif(shutil.which(os.environ.get("CXX", "c++")) is None, reason="no C++ compiler")


def _both(img: torch.Tensor, ref: torch.Tensor, threads: int = 2):
    """(fused map, its gradient), (torch map, its gradient) for a fixed random weighting."""
    w = torch.rand(img.shape, generator=torch.Generator().manual_seed(4), dtype=img.dtype)
    out = []
    for fused in (True, False):
        x = img.clone().requires_grad_()
        if fused:
            m = ssim_map_cpp(x.permute(2, 0, 1), ref.permute(2, 0, 1), SSIM_C1, SSIM_C2, threads).permute(1, 2, 0)
        else:
            m = ssim_map(x, ref)
        (m * w).sum().backward()
        out.append((m.detach(), x.grad))
    return out


@pytest.mark.parametrize("shape", [(37, 53, 3), (5, 4, 3), (64, 11, 1)])
def test_float64_values_and_gradients_match_ssim_map(shape):
    assert cpp_problem() is None
    gen = torch.Generator().manual_seed(sum(shape))
    img = torch.rand(shape, generator=gen, dtype=torch.float64)
    ref = (img + 0.1 * torch.randn(shape, generator=gen, dtype=torch.float64)).clamp(0, 1)
    (m, g), (m_ref, g_ref) = _both(img, ref)
    assert (m - m_ref).abs().max() <= 1e-12
    assert (g - g_ref).abs().max() <= 1e-12 * max(1.0, g_ref.abs().max().item())


def test_flat_and_identical_images():
    flat = torch.full((20, 24, 3), 0.5, dtype=torch.float64)
    (m, g), (m_ref, g_ref) = _both(flat, flat.clone())
    assert torch.allclose(m, torch.ones_like(m)) and torch.isfinite(g).all()
    assert (g - g_ref).abs().max() <= 1e-12
    black = torch.zeros(16, 16, 3, dtype=torch.float64)
    (m, g), (m_ref, g_ref) = _both(black, torch.ones_like(black))
    assert torch.isfinite(m).all() and torch.isfinite(g).all()
    assert (m - m_ref).abs().max() <= 1e-12 and (g - g_ref).abs().max() <= 1e-12


def test_float32_loss_and_gradient_close_to_the_torch_path():
    gen = torch.Generator().manual_seed(1)
    img = torch.rand(90, 120, 3, generator=gen, requires_grad=True)
    ref = torch.rand(90, 120, 3, generator=gen)
    fused = ssim(img, ref)  # the training loss takes the fused kernel on the CPU
    fused.backward()
    g_fused, img.grad = img.grad.clone(), None
    plain = ssim_map(img, ref).mean()
    plain.backward()
    assert abs(fused.item() - plain.item()) <= 1e-6
    assert (g_fused - img.grad).abs().max() <= 1e-5 * img.grad.abs().max()


def test_same_bits_at_1_2_and_4_threads():
    gen = torch.Generator().manual_seed(2)
    img, ref = torch.rand(3, 70, 90, generator=gen), torch.rand(3, 70, 90, generator=gen)
    results = []
    for threads in (1, 2, 4):
        x = img.clone().requires_grad_()
        m = ssim_map_cpp(x, ref, SSIM_C1, SSIM_C2, threads)
        m.sum().backward()
        results.append((m.detach(), x.grad))
    for m, g in results[1:]:
        assert torch.equal(m, results[0][0]) and torch.equal(g, results[0][1])


def test_gradcheck():
    gen = torch.Generator().manual_seed(3)
    img = torch.rand(2, 13, 15, generator=gen, dtype=torch.float64, requires_grad=True)
    ref = torch.rand(2, 13, 15, generator=gen, dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda x: ssim_map_cpp(x, ref, SSIM_C1, SSIM_C2, 2), [img])
