"""Blending diagnostics: the two-layer identity dC/dalpha = T (c - C_behind), the transmittance
factor on the screen-space gradient, and the scene-wide pairs against trace_pixel."""

from __future__ import annotations

import math

import pytest
import torch

from exploregs_plugin.analysis.branches import ViewProblem
from exploregs_plugin.analysis.blending import (
    blending_by_rank, composited_pairs, image_gradient, pixel_blending, screen_gradients,
)
from exploregs_plugin.cameras import Camera
from exploregs_plugin.model.gaussians import SH_C0
from exploregs_plugin.rasterizer import rasterize, trace_pixel
from exploregs_plugin.bench.components.raster_scenes import random_scene

F64 = torch.float64
W, H = 16, 12
X, Y = 7, 5  # the traced pixel


def _l1(image, target):
    return (image - target).abs().mean()


def _layers(alphas, colors, depths, offset=1.0):
    """Gaussians stacked on the ray of pixel (X, Y) (means 1 px to its right, so the screen-space
    gradient is not zero), isotropic, degree-0 colours; raw parameters, identity camera."""
    f = float(W)
    K = torch.tensor([[f, 0.0, W / 2], [0.0, f, H / 2], [0.0, 0.0, 1.0]], dtype=F64)
    u, v = X + 0.5 + offset, Y + 0.5
    means = torch.tensor([[(u - W / 2) / f * z, (v - H / 2) / f * z, z] for z in depths], dtype=F64)
    n = len(depths)
    # pixel-space sigma ~ 2 px at every depth: world sigma = 2 z / f
    scales = torch.tensor([[2.0 * z / f] * 3 for z in depths], dtype=F64)
    quats = torch.zeros(n, 4, dtype=F64)
    quats[:, 0] = 1.0
    rgb = torch.tensor(colors, dtype=F64)
    # alpha at the traced pixel = o exp(-0.5 (offset / sigma_px)^2) with the 0.3 px^2 low-pass
    g = math.exp(-0.5 * offset**2 / (4.0 + 0.3))
    opac = torch.tensor(alphas, dtype=F64) / g
    params = {"means": means, "quats": quats, "scales": torch.log(scales), "opacities": torch.logit(opac),
              "sh0": ((rgb - 0.5) / SH_C0)[:, None, :], "shN": torch.zeros(n, 0, 3, dtype=F64)}  # fmt: skip
    return params, Camera(torch.eye(4, dtype=F64), K, W, H, "layers")


def test_two_layer_dc_dalpha_and_back_layer_transmittance():
    a_front, a_back = 0.6, 0.7
    c_front, c_back = [0.9, 0.2, 0.1], [0.1, 0.5, 0.8]
    bg = torch.tensor([0.2, 0.3, 0.4], dtype=F64)
    params, camera = _layers([a_front, a_back], [c_front, c_back], [2.0, 3.0])
    target = torch.zeros(H, W, 3, dtype=F64)
    data = pixel_blending(ViewProblem(params, camera, target, 0, _l1, bg), X, Y)
    assert data["ids"].tolist() == [0, 1]
    # off the optical axis the projected footprint is not exactly isotropic: alpha is close to,
    # not exactly, the requested value; the identities below use the traced alphas
    assert torch.allclose(data["alphas"], torch.tensor([a_front, a_back], dtype=F64), rtol=1e-3)
    a_front, a_back = data["alphas"].tolist()
    t0, t1 = 1.0, 1.0 - a_front
    assert torch.allclose(data["T_before"], torch.tensor([t0, t1], dtype=F64))
    cf, cb = torch.tensor(c_front, dtype=F64), torch.tensor(c_back, dtype=F64)
    behind_front = a_back * cb + (1 - a_back) * bg  # C_{2:N}, seen through T_1
    want = torch.stack([t0 * (cf - behind_front), t1 * (cb - bg)])
    assert torch.allclose(data["dC_dalpha"], want, atol=1e-12)
    pixel = t0 * a_front * cf + t1 * a_back * cb + t1 * (1 - a_back) * bg
    assert torch.allclose(data["color"], pixel, atol=1e-12)

    # autograd: alpha_m = o_m G_m, so dC/do_m = dC/dalpha_m * G_m
    sh = torch.cat([params["sh0"], params["shN"]], 1)
    opac = torch.sigmoid(params["opacities"]).clone().requires_grad_(True)
    for ch in range(3):
        opac.grad = None
        image, *_ = rasterize(params["means"], params["quats"], torch.exp(params["scales"]), opac, sh,
                              camera, sh_degree=0, background=bg)  # fmt: skip
        image[Y, X, ch].backward()
        g = data["alphas"] / opac.detach()
        assert torch.allclose(opac.grad, want[:, ch] * g, atol=1e-12)

    # The back layer's screen-space gradient is attenuated by exactly T_before (what the figure
    # data lists): black background and the same back Gaussian with and without the front one.
    black = torch.zeros(3, dtype=F64)
    both = pixel_blending(ViewProblem(params, camera, target, 0, _l1, black), X, Y)
    alone_params = {k: v[1:] for k, v in params.items()}
    alone = pixel_blending(ViewProblem(alone_params, camera, target, 0, _l1, black), X, Y)
    assert alone["ids"].tolist() == [0] and float(alone["T_before"][0]) == 1.0
    ratio = float(both["grad_pixel"][1] / alone["grad_pixel"][0])
    assert ratio == pytest.approx(float(both["T_before"][1]), rel=1e-9)
    assert ratio == pytest.approx(1 - a_front, rel=1e-9)
    assert float(both["grad_pixel"][1]) > 0


def test_screen_gradients_are_in_ndc_units():
    params, camera = _layers([0.5, 0.5], [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], [2.0, 4.0])
    target = torch.zeros(H, W, 3, dtype=F64)
    grads = screen_gradients(ViewProblem(params, camera, target, 0, _l1))
    sh = torch.cat([params["sh0"], params["shN"]], 1)
    means = params["means"].clone().requires_grad_(True)
    image, _, _, info = rasterize(means, params["quats"], torch.exp(params["scales"]),
                                  torch.sigmoid(params["opacities"]), sh, camera, sh_degree=0)  # fmt: skip
    info["means2d"].retain_grad()
    _l1(image, target).backward()
    g = info["means2d"].grad
    want = torch.sqrt((g[:, 0] * W / 2) ** 2 + (g[:, 1] * H / 2) ** 2)
    assert torch.allclose(grads["image"], want, rtol=1e-12) and (want > 0).all()


def test_composited_pairs_match_trace_pixel():
    s = random_scene(60, 24, 20, torch.Generator().manual_seed(4), scale_range=(0.05, 0.3), dtype=F64)
    params = {"means": s.means, "quats": s.quats, "scales": torch.log(s.scales),
              "opacities": torch.logit(s.opacities), "sh0": s.sh_coeffs[:, :1], "shN": s.sh_coeffs[:, 1:]}
    camera = s.camera
    pairs = composited_pairs(params, camera)
    checked = 0
    for y in range(0, s.height, 3):
        for x in range(0, s.width, 3):
            tr = trace_pixel(*s.args(), x, y)
            here = pairs["pixel"] == y * s.width + x
            order = torch.argsort(pairs["rank"][here])
            assert pairs["ids"][here][order].tolist() == tr["ids"].tolist(), (x, y)
            assert pairs["rank"][here][order].tolist() == list(range(len(tr["ids"])))
            assert torch.allclose(pairs["T_before"][here][order], tr["T_before"], rtol=1e-10)
            assert torch.allclose(pairs["alphas"][here][order], tr["alphas"], rtol=1e-10)
            checked += len(tr["ids"])
    assert checked > 50


def test_blending_by_rank_means():
    pairs = {"pixel": torch.tensor([0, 0, 1, 1, 1, 2]), "ids": torch.tensor([0, 1, 2, 0, 1, 3]),
             "rank": torch.tensor([0, 1, 0, 1, 2, 0]),
             "T_before": torch.tensor([1.0, 0.5, 1.0, 0.25, 0.125, 1.0], dtype=F64)}  # fmt: skip
    grad = torch.tensor([4.0, 2.0, 8.0, 1.0], dtype=F64)
    out = blending_by_rank(pairs, grad, threshold=3.0)
    assert out["pixels"].tolist() == [3, 2, 1]
    assert torch.allclose(out["mean_grad"], torch.tensor([(4 + 8 + 1) / 3, (2 + 4) / 2, 2.0], dtype=F64))
    assert torch.allclose(out["mean_T"], torch.tensor([1.0, 0.375, 0.125], dtype=F64))
    assert torch.allclose(out["frac_above"], torch.tensor([2 / 3, 0.5, 0.0], dtype=F64))
    assert blending_by_rank(pairs, grad, max_rank=2)["rank"].tolist() == [0, 1]


def test_per_pixel_gradient_parts_sum_to_the_screen_space_gradient():
    s = random_scene(50, 20, 16, torch.Generator().manual_seed(8), scale_range=(0.05, 0.3), dtype=F64)
    params = {"means": s.means, "quats": s.quats, "scales": torch.log(s.scales),
              "opacities": torch.logit(s.opacities), "sh0": s.sh_coeffs[:, :1], "shN": s.sh_coeffs[:, 1:]}
    camera = s.camera
    bg = torch.tensor([0.1, 0.6, 0.3], dtype=F64)
    target = torch.rand(s.height, s.width, 3, generator=torch.Generator().manual_seed(1), dtype=F64)
    grad_c = image_gradient(ViewProblem(params, camera, target, 3, _l1, bg))
    pairs = composited_pairs(params, camera, sh_degree=3, background=bg, image_grad=grad_c)
    means = s.means.clone().requires_grad_(True)
    image, _, _, info = rasterize(means, s.quats, s.scales, s.opacities, s.sh_coeffs, s.camera, background=bg)  # fmt: skip
    info["means2d"].retain_grad()
    _l1(image, target).backward()
    summed = torch.zeros(50, 2, dtype=F64).index_add_(0, pairs["ids"], pairs["grad_px"])
    want = info["means2d"].grad
    assert want.abs().max() > 0
    assert torch.allclose(summed, want, rtol=1e-8, atol=1e-12 * float(want.abs().max()))
    prof = blending_by_rank(pairs, screen_gradients(ViewProblem(params, camera, target, 3, _l1, bg))["image"],
                            image_size=(s.width, s.height))  # fmt: skip
    assert (prof["mean_pixel_grad"] > 0).all() and prof["mean_pixel_grad"].shape == prof["mean_T"].shape
    # the pixel figure's "through this pixel" gradient is the same quantity at one pixel
    from exploregs_plugin.analysis.branches import ndc_gradient_norm

    busiest = int(torch.bincount(pairs["pixel"]).argmax())
    x, y = busiest % s.width, busiest // s.width
    at = pixel_blending(ViewProblem(params, camera, target, 3, _l1, bg), x, y)
    here = pairs["pixel"] == busiest
    order = torch.argsort(pairs["rank"][here])
    want_px = ndc_gradient_norm(pairs["grad_px"][here][order], s.width, s.height)
    assert len(at["ids"]) >= 3 and torch.allclose(at["grad_pixel"], want_px, rtol=1e-8, atol=1e-15)
    with pytest.raises(ValueError, match="image_size"):
        blending_by_rank(pairs, torch.zeros(50, dtype=F64))


def test_blending_by_visibility_bins_each_gaussian_by_its_best_transmittance():
    from exploregs_plugin.analysis.blending import blending_by_visibility

    pairs = {"ids": torch.tensor([0, 0, 1, 2, 2]), "T_before": torch.tensor([0.005, 0.8, 0.05, 0.0005, 0.002], dtype=F64)}
    grad = torch.tensor([3.0, 1.0, 0.5, 7.0], dtype=F64)  # Gaussian 3 is never blended
    out = blending_by_visibility(pairs, grad, threshold=0.8, edges=(0.0, 0.01, 0.5, 1.0 + 1e-9))
    assert out["gaussians"].tolist() == [1, 1, 1]  # best T: 0.8, 0.05, 0.002
    assert torch.allclose(out["mean_grad"], torch.tensor([0.5, 1.0, 3.0], dtype=F64))
    assert torch.allclose(out["frac_above"], torch.tensor([0.0, 1.0, 1.0], dtype=F64))
    assert out["hi"][-1] == 1.0


@pytest.mark.parametrize("backend", ["torch", "cpp"])
@pytest.mark.parametrize("workers", [1, 2])
def test_rasterizer_visibility_sums_equal_the_blended_pairs(workers, backend):
    from exploregs_plugin.rasterizer import RasterSettings, rasterize

    s = random_scene(80, 40, 32, torch.Generator().manual_seed(5), scale_range=(0.05, 0.3), dtype=F64)
    params = {"means": s.means, "quats": s.quats, "scales": torch.log(s.scales),
              "opacities": torch.logit(s.opacities), "sh0": s.sh_coeffs[:, :1], "shN": s.sh_coeffs[:, 1:]}
    pairs = composited_pairs(params, s.camera)
    weight = torch.zeros(80, dtype=F64).index_add_(0, pairs["ids"], pairs["T_before"] * pairs["alphas"])
    alpha = torch.zeros(80, dtype=F64).index_add_(0, pairs["ids"], pairs["alphas"])
    peak = torch.zeros(80, dtype=F64).scatter_reduce_(0, pairs["ids"], pairs["T_before"] * pairs["alphas"], "amax")
    if backend == "cpp":
        from exploregs_plugin.kernels import cpp_problem

        if cpp_problem():
            pytest.skip(cpp_problem())
    settings = RasterSettings(backend=backend, visibility_stats=True, workers=workers, chunk_elements=2048)
    image, _, _, info = rasterize(*s.args(), settings=settings)
    assert info["visibility"].shape == (80, 3) and (weight > 0).sum() > 20
    assert torch.allclose(info["visibility"][:, 0], weight, rtol=1e-9, atol=1e-12)
    assert torch.allclose(info["visibility"][:, 1], alpha, rtol=1e-9, atol=1e-12)
    # the peak: the largest weight at one pixel, spread over several tiles and (torch) workers' chunks
    assert torch.allclose(info["visibility"][:, 2], peak, rtol=1e-9, atol=1e-12)
    assert (peak < weight - 1e-6).sum() > 20 and (peak > 0.5).sum() > 3  # neither the sum nor trivial
    plain, _, _, plain_info = rasterize(*s.args(), settings=RasterSettings(backend=backend, workers=workers,
                                                                           chunk_elements=2048))
    assert torch.equal(plain, image) and "visibility" not in plain_info  # the image does not change
