"""The opacity-aware support box: narrower than the sigma_radius box where a Gaussian is faint,
never narrow enough to drop a pixel whose alpha reaches alpha_min, so images and gradients are
those of the sigma_radius box with fewer pairs to composite."""

from __future__ import annotations

import importlib
import math
import os
import shutil
from dataclasses import replace

import pytest
import torch

from exploregs_plugin.bench.components.raster_scenes import random_scene
from exploregs_plugin.rasterizer import RasterSettings, rasterize
from exploregs_plugin.rasterizer.cpp_backend import project_cpp
from exploregs_plugin.rasterizer.projection import opacity_support, project_gaussians

ALPHA_MIN = 1.0 / 255.0
rasterize_module = importlib.import_module("exploregs_plugin.rasterizer.rasterize")  # the package exports the function
needs_cpp = pytest.mark.skipif(shutil.which(os.environ.get("CXX", "c++")) is None,
                               reason="no C++ compiler on this machine")


def _covariances(n: int, g: torch.Generator) -> torch.Tensor:
    """[n, 3] (a, b, c) of random 2D covariances, eps2d included, axes 0.55 to 30 px, any angle."""
    sd = 0.55 * torch.exp(torch.rand(n, 2, generator=g, dtype=torch.float64) * math.log(30 / 0.55))
    th = torch.rand(n, generator=g, dtype=torch.float64) * math.pi
    cs, sn = torch.cos(th), torch.sin(th)
    a = (cs * sd[:, 0]) ** 2 + (sn * sd[:, 1]) ** 2
    c = (sn * sd[:, 0]) ** 2 + (cs * sd[:, 1]) ** 2
    b = cs * sn * (sd[:, 0] ** 2 - sd[:, 1] ** 2)
    return torch.stack([a, b, c], -1)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_every_pixel_whose_alpha_reaches_alpha_min_lies_inside_the_narrowed_box(dtype):
    g = torch.Generator().manual_seed(3)
    n = 400
    abc = _covariances(n, g)
    # opacities across the range, and just above alpha_min, where the box shrinks to a pixel
    opac = torch.cat([ALPHA_MIN * (1 + torch.rand(40, generator=g, dtype=torch.float64) * 1e-3),
                      torch.exp(torch.rand(n - 40, generator=g, dtype=torch.float64) * math.log(ALPHA_MIN))])
    opac = opac.clamp(ALPHA_MIN, 0.99)
    var = abc[:, [0, 2]]
    box = torch.ceil(3.0 * torch.sqrt(var))
    support = opacity_support(box.to(dtype), var.to(dtype), opac.to(dtype), torch.ones(n, dtype=torch.bool),
                              ALPHA_MIN).double()
    assert (support <= box).all() and (support >= 1).all()
    # narrower exactly where t = 2 ln(o / alpha_min) < 9 leaves room, not where o >= exp(4.5) alpha_min
    # (o < 0.05: sqrt(t) < 2.26, at least 1.7 px under the box where that is 8 px or more)
    faint, opaque = (opac < 0.05)[:, None] & (box >= 8), opac > math.exp(4.5) * ALPHA_MIN * 1.01
    assert faint.sum() > 50 and (support[faint] < box[faint]).all() and torch.equal(support[opaque], box[opaque])
    det = abc[:, 0] * abc[:, 2] - abc[:, 1] ** 2
    conic = torch.stack([abc[:, 2], -abc[:, 1], abc[:, 0]], -1) / det[:, None]
    for i in range(n):
        # pixel centres at random sub-pixel offsets of the mean, over the whole sigma box
        r = int(box[i].max())
        off = torch.rand(2, generator=g, dtype=torch.float64) - 0.5
        d = torch.arange(-r, r + 1, dtype=torch.float64)
        dx, dy = torch.meshgrid(d + off[0], d + off[1], indexing="xy")
        q = conic[i, 0] * dx * dx + 2 * conic[i, 1] * dx * dy + conic[i, 2] * dy * dy
        reached = opac[i] * torch.exp(-0.5 * q) >= ALPHA_MIN
        inside = (dx.abs() <= support[i, 0]) & (dy.abs() <= support[i, 1])
        in_sigma_box = (dx.abs() <= box[i, 0]) & (dy.abs() <= box[i, 1])
        assert not (reached & in_sigma_box & ~inside).any(), (i, float(opac[i]), abc[i].tolist())


def test_a_floored_determinant_or_a_nan_keeps_the_sigma_box():
    box = torch.tensor([[6.0, 9.0], [4.0, 4.0], [5.0, 5.0]])
    var = torch.tensor([[4.0, 9.0], [float("nan"), 1.0], [1.0, 1.0]])
    opac = torch.tensor([0.02, 0.02, float("nan")])
    exact = torch.tensor([False, True, True])
    got = opacity_support(box, var, opac, exact, ALPHA_MIN)
    assert torch.equal(got[0], box[0]) and got[1, 0] == 4.0 and got[1, 1] < 4.0 and torch.equal(got[2], box[2])


def _render(scene, settings, sigma_box: bool, monkeypatch):
    """Image, alpha, depth, pair count and every gradient; ``sigma_box``: composite with the
    sigma_radius box (``radii``) instead of the narrowed support. The compiled path bins every tile
    of the box (the tiles its ellipse misses are the subject of the test below)."""
    real_bins = rasterize_module.CppBins
    monkeypatch.setattr(rasterize_module, "CppBins", lambda *args: real_bins(*args[:7]))
    for name in ("_composite_visible", "_composite_compiled"):  # the torch and the compiled path
        def composite(proj, *args, real=getattr(rasterize_module, name)):
            if sigma_box:
                proj = replace(proj, support=proj.radii.to(proj.means2d.dtype))
            return real(proj, *args)

        monkeypatch.setattr(rasterize_module, name, composite)
    params = [t.detach().float().clone().requires_grad_() for t in
              (scene.means, scene.quats, scene.scales, scene.opacities, scene.sh_coeffs)]  # fmt: skip
    image, alpha, depth, info = rasterize(*params, scene.camera.to(torch.float32), settings=settings)
    w = torch.randn(scene.height, scene.width, 5, generator=torch.Generator().manual_seed(1))
    ((image * w[..., :3]).sum() + (alpha * w[..., 3:4]).sum() + (depth * w[..., 4:]).sum()).backward()
    return [t.detach() for t in (image, alpha, depth, *(p.grad for p in params))], info["n_pairs"]


@pytest.mark.parametrize("backend", [pytest.param("cpp", marks=needs_cpp), "torch"])
def test_the_narrowed_box_changes_no_pixel_and_no_gradient_only_the_pair_count(backend, monkeypatch):
    scene = random_scene(1500, 96, 80, torch.Generator().manual_seed(5), scale_range=(0.01, 0.08))
    # faint Gaussians, as after an opacity reset, beside opaque ones
    scene = replace(scene, opacities=torch.where(torch.arange(1500) % 2 == 0, 0.01, scene.opacities))
    settings = RasterSettings(backend=backend, workers=2)
    narrow, pairs = _render(scene, settings, False, monkeypatch)
    wide, wide_pairs = _render(scene, settings, True, monkeypatch)
    assert pairs < 0.9 * wide_pairs
    for got, ref in zip(narrow, wide):
        if backend == "cpp":  # the same pairs in the same order: the same bits
            assert torch.equal(got, ref)
        else:  # the torch compositor pads its chunks to other sizes: the same up to rounding
            assert float((got - ref).abs().max()) <= 1e-5 * float(ref.abs().max()), float((got - ref).abs().max() / ref.abs().max())


@needs_cpp
def test_the_compiled_projection_narrows_as_the_torch_one_does():
    scene = random_scene(3000, 128, 96, torch.Generator().manual_seed(2))
    scene = replace(scene, opacities=torch.linspace(0.003, 0.999, 3000, dtype=torch.float64))
    args = [t.float() for t in (scene.means, scene.quats, scene.scales, scene.opacities)]
    viewmat, K = scene.viewmat.float(), scene.K.float()
    for settings in (RasterSettings(), RasterSettings(antialiased=True)):
        ref = project_gaussians(*args, viewmat, K, 128, 96, 0.01, 1e10, settings)
        got = project_cpp(*args, viewmat, K, 128, 96, 0.01, 1e10, settings, 2)
        vis = ref.visible
        assert torch.equal(got.radii, ref.radii) and (ref.support[vis] < ref.radii[vis]).any()
        # log and sqrt may round differently in C++: a ceil may land one pixel apart, rarely
        differ = (got.support[vis] != ref.support[vis]).any(-1)
        assert float((got.support[vis] - ref.support[vis]).abs().max()) <= 1 and int(differ.sum()) <= 3


def _composite_both_ways(means2d, conics, opac, feats, support, depths, width, height, dtype, settings):
    """Image, visibility statistics, every input's gradient and the pair count of the compiled
    compositor, binned with every tile of the support box and with the tiles the ellipse reaches."""
    from exploregs_plugin.rasterizer.cpp_backend import CppBins, composite_cpp

    weights = torch.randn(height, width, feats.shape[1] + 1, generator=torch.Generator().manual_seed(9)).to(dtype)
    results = []
    for culled in (False, True):
        leaves = [t.detach().to(dtype).clone().requires_grad_() for t in (means2d, conics, opac, feats)]
        extra = (leaves[1].detach(), leaves[2].detach(), settings.alpha_min) if culled else ()
        bins = CppBins(leaves[0].detach(), support.to(dtype), depths.to(dtype), width, height, settings.tile_size,
                       None, *extra)
        out, visibility = composite_cpp(*leaves, support.to(dtype), bins, settings, 2)
        (out * weights).sum().backward()
        results.append(([out.detach(), visibility, *(t.grad for t in leaves), leaves[0].absgrad], bins))
    return results


@needs_cpp
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_tiles_of_the_box_that_the_ellipse_misses_are_left_out_and_nothing_changes(dtype):
    """A tile of a Gaussian's support box whose pixel centres all lie outside its ellipse
    q <= 2 ln(o / alpha_min) would add exact zeros: binned without it, the compiled compositor gives
    the same image, statistics and gradients bit for bit, from fewer pairs. Elongated and rotated
    Gaussians, faint ones, ones fainter than alpha_min, and axis-aligned ones whose ellipse reaches
    the first pixel centre of the next tile by a relative 1e-4 to 1e-7 in q, short of it or past it."""
    g = torch.Generator().manual_seed(12)
    width, height, ts = 64, 48, 8
    n = 600
    abc = _covariances(n, g)
    det = abc[:, 0] * abc[:, 2] - abc[:, 1] ** 2
    conics = torch.stack([abc[:, 2], -abc[:, 1], abc[:, 0]], -1) / det[:, None]
    opac = torch.exp(torch.rand(n, generator=g, dtype=torch.float64) * math.log(ALPHA_MIN / 1.2)).clamp(max=0.99)
    means2d = torch.rand(n, 2, generator=g, dtype=torch.float64) * torch.tensor([width, height])
    # at the tile edge: mean (x0 - d, y0) with y0 a pixel row, B = 0 and q at the centre (x0, y0) of
    # the next tile's first column = t (1 + eps): the pixel paints (eps < 0) or just misses
    edge, must_keep = [], []  # (row, tile) pairs that hold a pixel where alpha >= alpha_min
    for i, eps in enumerate([-1e-4, -1e-5, -1e-6, -1e-7, 1e-7, 1e-6, 1e-4] * 6):
        a_cov = float(torch.exp(torch.rand(1, generator=g) * 4.0))  # sigma 1 to 7.4 px
        o = float(0.02 + 0.9 * torch.rand(1, generator=g))
        t = 2 * math.log(o / ALPHA_MIN)
        tile_x, row = 1 + i % 6, 1 + (i // 6) % 5
        x0, y0 = tile_x * ts + 0.5, row * ts + 0.5
        edge.append((x0 - math.sqrt(t * (1 + eps) * a_cov), y0, 1 / a_cov, 1 / (0.5 * a_cov), o))
        if eps < 0:
            must_keep.append((n + i, row * (width // ts) + tile_x))
    edge = torch.tensor(edge, dtype=torch.float64)
    means2d = torch.cat([means2d, edge[:, :2]])
    conics = torch.cat([conics, torch.stack([edge[:, 2], torch.zeros(len(edge), dtype=torch.float64), edge[:, 3]], -1)])
    opac = torch.cat([opac, edge[:, 4]])
    var = torch.stack([conics[:, 2], conics[:, 0]], -1) / (conics[:, 0] * conics[:, 2] - conics[:, 1] ** 2)[:, None]
    box = torch.ceil(3.0 * torch.sqrt(var))
    m = len(opac)
    # the narrowed box for half of the rows, the sigma box (wider than the ellipse) for the others
    support = torch.where((torch.arange(m) % 2 == 0)[:, None],
                          opacity_support(box, var, opac, torch.ones(m, dtype=torch.bool), ALPHA_MIN), box)
    support[n:] = 4.0 * torch.sqrt(var[n:])  # the edge rows: a box that holds the next tile's column
    feats = torch.rand(m, 4, generator=g, dtype=torch.float64)
    depths = torch.rand(m, generator=g, dtype=torch.float64)
    settings = RasterSettings(backend="cpp", tile_size=ts, absgrad=True, visibility_stats=True)
    (box_out, box_bins), (cull_out, cull_bins) = _composite_both_ways(
        means2d, conics, opac, feats, support, depths, width, height, dtype, settings)
    assert cull_bins.n_pairs < 0.9 * box_bins.n_pairs and box_out[0][..., 3].max() > 0.5
    for got, ref in zip(cull_out, box_out):
        assert torch.equal(got, ref)
    off, pairs = cull_bins.tile_offsets, cull_bins.pair_gauss
    for row, tile in must_keep:
        assert (pairs[off[tile]:off[tile + 1]] == row).any(), (row, tile)
    # rows fainter than alpha_min (the first n rows hold some) paint nothing: each keeps at most the
    # tiles around its mean that the margin holds
    faint = torch.nonzero(opac[:n] < ALPHA_MIN * 0.99).squeeze(1)
    kept, boxed = cull_bins.gauss_count[faint], box_bins.gauss_count[faint]
    assert len(faint) >= 10 and (kept <= 4).all() and kept.sum() < 0.5 * boxed.sum()
