"""Guided seeding and occlusion-aware splitting: the pure functions behind the operators."""

from __future__ import annotations

import math

import pytest
import torch

from exploregs_plugin.strategies import StrategyError
from exploregs_plugin.strategies.guided import coarse_view, guided_seed_rows, stratified_depths
from exploregs_plugin.strategies.occlusion import mean_transmittance, occlusion_weights
from exploregs_plugin.rasterizer.sh import SH_C0


def _view(error: torch.Tensor, colour: torch.Tensor, viewmat: torch.Tensor, f: float = 20.0) -> dict:
    h, w = error.shape
    K = torch.tensor([[f, 0.0, 2.0 * w], [0.0, f, 2.0 * h], [0.0, 0.0, 1.0]])
    return {"error": error, "colour": colour, "viewmat": viewmat, "K": K,
            "size": torch.tensor([4.0 * w, 4.0 * h]), "cell": torch.tensor(4.0)}


def test_stratified_depths_share_the_range_evenly():
    gen = torch.Generator().manual_seed(0)
    near, far = torch.full((1000,), 0.1), torch.full((1000,), 40.0)
    log_z = stratified_depths(1000, near, far, "log", gen)
    assert bool(((log_z >= 0.1) & (log_z <= 40.0)).all())
    # one sample per stratum: exactly half below the geometric middle, a quarter per quartile
    assert int((log_z < math.sqrt(0.1 * 40.0)).sum()) == 500
    assert int((log_z > 0.1 * (400.0 ** 0.75)).sum()) == 250
    inv_z = stratified_depths(1000, near, far, "inverse", gen)
    harmonic = 1.0 / (0.5 * (1 / 0.1 + 1 / 40.0))
    assert int((inv_z < harmonic).sum()) == 500
    assert float((inv_z > 10.0).float().mean()) < 0.02 < float((log_z > 10.0).float().mean())
    with pytest.raises(StrategyError, match="guide_depth"):
        stratified_depths(4, near[:4], far[:4], "linear", gen)


def test_guided_seeds_go_through_the_worst_cell_with_its_colour():
    error = torch.full((6, 8), 1e-4)
    error[2, 5] = 1.0  # one bad cell (cell size 4: pixels x 20..24, y 8..12)
    colour = torch.zeros(6, 8, 3)
    colour[2, 5] = torch.tensor([0.9, 0.2, 0.1])
    viewmat = torch.eye(4)
    viewmat[:3, 3] = torch.tensor([0.0, 0.0, 1.0])  # camera at z = -1 in the world
    views = {3: _view(error, colour, viewmat)}
    means = torch.randn(50, 3, generator=torch.Generator().manual_seed(1)) * 2.0 + torch.tensor([0.0, 0.0, 6.0])
    rows = guided_seed_rows(views, 40, torch.Generator().manual_seed(2), means, 3, power=2.0, near=0.5,
                            far=20.0, depth="log", opacity=0.3, scale_mult=1.0)
    cam = rows["means"] + viewmat[:3, 3]
    z = cam[:, 2]
    K = views[3]["K"]
    u, v = K[0, 0] * cam[:, 0] / z + K[0, 2], K[1, 1] * cam[:, 1] / z + K[1, 2]
    assert bool(((u >= 20) & (u <= 24) & (v >= 8) & (v <= 12)).all())  # inside the bad cell
    assert bool(((z >= 0.5 - 1e-5) & (z <= 20.0 + 1e-5)).all())
    assert torch.allclose(rows["sh0"][:, 0] * SH_C0 + 0.5, torch.tensor([0.9, 0.2, 0.1]).expand(40, 3), atol=1e-6)
    # a seed covers its cell's footprint at its depth
    assert torch.allclose(torch.exp(rows["scales"][:, 0]), z * 4 / 20.0, rtol=1e-5)
    assert torch.allclose(torch.sigmoid(rows["opacities"]), torch.full((40,), 0.3), atol=1e-6)
    assert rows["shN"].shape == (40, 3, 3) and torch.allclose(rows["quats"].norm(dim=-1), torch.ones(40), atol=1e-6)
    # far bound from the Gaussians' box when guide_far is unset: reaches its farthest corner
    auto = guided_seed_rows(views, 200, torch.Generator().manual_seed(3), means, 0, power=2.0, near=0.5,
                            far=None, depth="log", opacity=0.3, scale_mult=1.0)
    corner_far = float((means.max(0).values[2] + 1.0))
    assert float((auto["means"][:, 2] + 1.0).max()) <= corner_far * (1 + 1e-5)
    assert float((auto["means"][:, 2] + 1.0).max()) > 0.5 * corner_far
    assert guided_seed_rows({}, 5, torch.Generator(), means, 0, power=2.0, near=0.5, far=None,
                            depth="log", opacity=0.3, scale_mult=1.0) is None


def test_coarse_view_averages_cells():
    error = torch.arange(36.0).reshape(6, 6)
    target = torch.ones(6, 6, 3) * 0.5
    e, c = coarse_view(error, target, 4)
    assert e.shape == (2, 2) and c.shape == (2, 2, 3)
    assert float(e[0, 0]) == pytest.approx(float(error[:4, :4].mean()))
    assert float(e[1, 1]) == pytest.approx(float(error[4:, 4:].mean()))  # the partial edge cell
    assert torch.allclose(c, torch.full((2, 2, 3), 0.5))


def test_occlusion_weights_prefer_hidden_gaussians_with_error():
    log_scales = torch.log(torch.tensor([[0.1] * 3, [0.1] * 3, [0.1] * 3, [0.4] * 3]))
    vis_weight = torch.tensor([5.0, 1.0, 1.0, 1.0])  # weight sums alpha T
    vis_alpha = torch.tensor([5.0, 5.0, 0.0, 5.0])  # alpha sums: T-bar 1, 0.2, unseen, 0.2
    error = torch.tensor([2.0, 2.0, 2.0, 0.0])
    t = mean_transmittance(vis_weight, vis_alpha)
    assert torch.allclose(t, torch.tensor([1.0, 0.2, 1.0, 0.2]))
    w = occlusion_weights(log_scales, vis_weight, vis_alpha, error)
    assert w[0] == 0 and w[2] == 0 and w[3] == 0 and w[1] == pytest.approx(0.1 * 0.8 * 2.0)


def test_the_cell_grows_on_large_images_so_maps_stay_small():
    from exploregs_plugin.strategies.guided import MAX_CELLS_PER_SIDE, view_cell

    assert view_cell(4, 144, 108) == 4
    assert view_cell(4, 1920, 1080) == 15 and math.ceil(1920 / 15) <= MAX_CELLS_PER_SIDE
    e, c = coarse_view(torch.rand(1080, 1920), torch.rand(1080, 1920, 3), view_cell(4, 1920, 1080))
    assert e.shape == (72, 128) and c.shape == (72, 128, 3)
