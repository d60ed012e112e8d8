"""Loss and metric maths against independent evaluations."""

import math

import numpy as np
import pytest
import torch

from exploregs_plugin.model.losses import VIEW_PSNR, photometric_loss, psnr, ssim, ssim_map
from exploregs_plugin.model.optim import OptimizerConfig


def _ssim_numpy(x: np.ndarray, y: np.ndarray) -> float:
    """Direct windowed evaluation of SSIM (zero padding), independent of the conv code."""
    size, sigma = 11, 1.5
    c = np.arange(size) - (size - 1) / 2
    g = np.exp(-c**2 / (2 * sigma**2)); g /= g.sum(); w = np.outer(g, g)
    h, wd, ch = x.shape
    pad = size // 2
    xp = np.pad(x, ((pad, pad), (pad, pad), (0, 0))); yp = np.pad(y, ((pad, pad), (pad, pad), (0, 0)))
    total = 0.0
    for i in range(h):
        for j in range(wd):
            px = xp[i:i + size, j:j + size]; py = yp[i:i + size, j:j + size]
            for k in range(ch):
                a, b = px[..., k], py[..., k]
                mx, my = (w * a).sum(), (w * b).sum()
                vx = (w * a * a).sum() - mx**2; vy = (w * b * b).sum() - my**2; cxy = (w * a * b).sum() - mx * my
                total += ((2 * mx * my + 1e-4) * (2 * cxy + 9e-4)) / ((mx**2 + my**2 + 1e-4) * (vx + vy + 9e-4))
    return total / (h * wd * ch)


def test_ssim_matches_direct_evaluation():
    gen = torch.Generator().manual_seed(0)
    x = torch.rand(13, 17, 3, generator=gen, dtype=torch.float64)
    y = (x + 0.2 * torch.rand(13, 17, 3, generator=gen, dtype=torch.float64)).clamp(0, 1)
    assert abs(float(ssim(x, y)) - _ssim_numpy(x.numpy(), y.numpy())) < 1e-10
    assert torch.allclose(ssim_map(x, x), torch.ones_like(x))


def test_psnr_values_and_region_mask():
    a = torch.zeros(4, 4, 3)
    b = torch.full((4, 4, 3), 0.1)
    assert math.isclose(psnr(a, b), 20.0, rel_tol=1e-6)  # mse 0.01 -> 20 dB
    assert psnr(a, a) == 100.0  # floored, not inf
    mask = torch.zeros(4, 4, dtype=torch.bool)
    mask[0, 0] = True
    b2 = b.clone(); b2[0, 0] = 0.0
    assert psnr(a, b2, mask) == 100.0
    assert math.isnan(psnr(a, b, torch.zeros(4, 4, dtype=torch.bool)))


def test_photometric_loss_is_the_3dgs_mix():
    gen = torch.Generator().manual_seed(1)
    x, y = torch.rand(16, 16, 3, generator=gen), torch.rand(16, 16, 3, generator=gen)
    loss, terms = photometric_loss(x, y, 0.2)
    expected = 0.8 * (x - y).abs().mean() + 0.2 * (1 - ssim(x, y))
    assert torch.allclose(loss, expected)
    assert set(terms) - {VIEW_PSNR} == {"l1", "dssim"}  # and the view's PSNR where the compiled loss ran
    assert torch.allclose(terms["l1"], (x - y).abs().mean()) and torch.allclose(terms["dssim"], 1 - ssim(x, y))


def test_means_lr_decays_exponentially_to_one_hundredth():
    cfg = OptimizerConfig()
    extent = 2.5
    assert math.isclose(cfg.means_lr_at(0, 1000, extent), 1.6e-4 * extent)
    assert math.isclose(cfg.means_lr_at(1000, 1000, extent), 1.6e-6 * extent)
    assert math.isclose(cfg.means_lr_at(500, 1000, extent), 1.6e-5 * extent, rel_tol=1e-9)


def test_depth_l1_in_depth_and_inverse_space():
    from exploregs_plugin.model.losses import depth_l1

    depth = torch.tensor([[2.0], [4.0], [0.0], [5.0]]).reshape(2, 2, 1).requires_grad_(True)
    target = torch.tensor([[1.0], [8.0], [3.0], [float("nan")]]).reshape(2, 2, 1)
    # z space: pixels 0..2 have a target (the rendered 0 counts as an error of 3); pixel 3 has none.
    assert math.isclose(float(depth_l1(depth, target).detach()), (1.0 + 4.0 + 3.0) / 3, rel_tol=1e-6)
    # 1/z space: the unrendered pixel is left out too; |1/2 - 1| and |1/4 - 1/8|.
    loss = depth_l1(depth, target, "inverse")
    assert math.isclose(float(loss.detach()), (0.5 + 0.125) / 2, rel_tol=1e-6)
    loss.backward()
    grad = depth.grad.reshape(-1)
    # d|1/d - 1/t|/dd = -sign(1/d - 1/t) / d^2, averaged over the two pixels.
    torch.testing.assert_close(grad, torch.tensor([0.5 * 0.25, -0.5 / 16, 0.0, 0.0]))
    assert bool(torch.isfinite(grad).all())
    # No usable pixel: zero, still differentiable.
    empty = depth_l1(depth, torch.zeros(2, 2, 1), "inverse")
    assert float(empty.detach()) == 0.0 and empty.requires_grad
    with pytest.raises(ValueError, match="'depth' or 'inverse'"):
        depth_l1(depth, target, "log")


def test_ms_ssim_levels_and_limits():
    from exploregs_plugin.model.losses import ms_ssim_levels

    assert ms_ssim_levels(256, 256) == 5
    assert ms_ssim_levels(72, 96) == 3  # 72 -> 36 -> 18; 9 px would be narrower than the window
    assert ms_ssim_levels(11, 40) == 1


def test_ms_ssim_values():
    import torch.nn.functional as F

    from exploregs_plugin.model.losses import SSIM_C1, SSIM_C2, SSIM_WINDOW, _gaussian_kernel_1d, ms_ssim

    gen = torch.Generator().manual_seed(0)
    a = torch.rand(20, 30, 3, generator=gen, dtype=torch.float64)
    b = (a + 0.05 * torch.randn(a.shape, generator=gen, dtype=torch.float64)).clamp(0, 1)
    assert ms_ssim(a, a) == pytest.approx(1.0)
    # one scale (min side 20 < 2 x 11): the mean SSIM over the windows inside the image
    g = _gaussian_kernel_1d(SSIM_WINDOW, 1.5, torch.float64, a.device)
    window = (g[:, None] * g[None, :])[None, None].expand(3, 1, -1, -1)

    def blur(t):
        return F.conv2d(t.permute(2, 0, 1)[None], window, groups=3)[0]

    mx, my = blur(a), blur(b)
    sxx, syy, sxy = blur(a * a) - mx**2, blur(b * b) - my**2, blur(a * b) - mx * my
    ssim_valid = (2 * mx * my + SSIM_C1) * (2 * sxy + SSIM_C2) / ((mx**2 + my**2 + SSIM_C1) * (sxx + syy + SSIM_C2))
    assert ms_ssim(a, b) == pytest.approx(float(ssim_valid.mean()), rel=1e-9)
    # more noise, lower score; the whole image as a region is the image's score
    worse = (a + 0.2 * torch.randn(a.shape, generator=gen, dtype=torch.float64)).clamp(0, 1)
    assert ms_ssim(a, worse) < ms_ssim(a, b) < 1.0
    big = torch.rand(64, 64, 3, generator=gen, dtype=torch.float64)  # two scales
    assert 0.0 < ms_ssim(big, (big + 0.05).clamp(0, 1)) < 1.0 and ms_ssim(big, big) == pytest.approx(1.0)
    assert ms_ssim(a, b, torch.ones(20, 30, dtype=torch.bool)) == pytest.approx(ms_ssim(a, b))
    # a region no window centre touches is NaN; an error restricted to a region shows there only
    edge = torch.zeros(20, 30, dtype=torch.bool)
    edge[:, :2] = True
    assert math.isnan(ms_ssim(a, b, edge))
    half = torch.zeros(20, 30, dtype=torch.bool)
    half[:, :15] = True
    spoiled = a.clone()
    spoiled[:, 18:] = worse[:, 18:]
    assert ms_ssim(a, spoiled, half) > ms_ssim(a, spoiled, ~half)
    with pytest.raises(ValueError, match="at least 11 px"):
        ms_ssim(a[:8], b[:8])


def test_ms_ssim_of_several_regions_in_one_pass_equals_one_by_one():
    from exploregs_plugin.model.losses import ms_ssim, ms_ssim_many

    gen = torch.Generator().manual_seed(2)
    a = torch.rand(64, 80, 3, generator=gen, dtype=torch.float64)
    b = (a + 0.1 * torch.randn(a.shape, generator=gen, dtype=torch.float64)).clamp(0, 1)
    top = torch.zeros(64, 80, dtype=torch.bool)
    top[:6] = True  # a band along the border: fewer scales than the image
    blob = torch.zeros(64, 80, dtype=torch.bool)
    blob[20:45, 30:70] = True
    masks = [None, top, blob, torch.zeros(64, 80, dtype=torch.bool)]
    many = ms_ssim_many(a, b, masks)
    for mask, value in zip(masks[:3], many):
        assert value == ms_ssim(a, b, mask)
    assert math.isnan(many[3])
