"""The initial Gaussians' scales: the mean distance to the 3 nearest points, wherever the cloud lies."""

from __future__ import annotations

import pytest
import torch

from exploregs_plugin.model.gaussians import init_params, knn_mean_distance


def _exact(points: torch.Tensor, k: int = 3) -> torch.Tensor:
    p = points.double()
    d = ((p[:, None, :] - p[None, :, :]) ** 2).sum(-1).sqrt()
    return d.topk(k + 1, dim=1, largest=False).values[:, 1:].mean(dim=1)


@pytest.mark.parametrize("offset", [0.0, 100.0, 1.0e4])
def test_the_3nn_distance_does_not_depend_on_where_the_cloud_lies(offset):
    """A unit cube of 3000 points, at the origin and far from it (a georeferenced capture): the
    distances are those of float64 differences, to float32 rounding of the coordinates. By a matrix
    product (|a|^2 + |b|^2 - 2 a.b) they were off by up to 150% at 100 and a quarter of them 0."""
    g = torch.Generator().manual_seed(0)
    cube = torch.rand(3000, 3, generator=g)
    points = cube + offset
    got = knn_mean_distance(points, chunk=1024)  # chunks: the rows are not taken in one block
    want = _exact(points)
    ulp = torch.finfo(torch.float32).eps * max(offset, 1.0)
    assert got.dtype == torch.float32 and got.shape == (3000,)
    assert (got > 0).all()
    assert torch.allclose(got.double(), want, rtol=1e-5, atol=4 * ulp), (got.double() - want).abs().max()
    assert float(want.mean()) == pytest.approx(0.054, abs=0.005)  # the cube's spacing, not a rounding


def test_initial_scales_are_the_log_of_the_3nn_distance_far_from_the_origin():
    points = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 2, 0], [0, 0, 3], [0, 0, 3]]) + 1000.0
    params = init_params(points, torch.full((5, 3), 0.5), sh_degree=1, opacity=0.1, scale_mult=1.0)
    dist = torch.exp(params["scales"][:, 0].detach())
    # point 0: its neighbours at 1, 2 and 3 (either copy of the last); point 1: at 1, sqrt(5), sqrt(10)
    assert dist[0].item() == pytest.approx(2.0, rel=1e-5)
    assert dist[1].item() == pytest.approx((1 + 5 ** 0.5 + 10 ** 0.5) / 3, rel=1e-5)
    # a coincident pair: its twin at 0 counts as a neighbour (then 3 and sqrt(10))
    assert dist[3].item() == dist[4].item() == pytest.approx((0 + 3 + 10 ** 0.5) / 3, rel=1e-5)
    assert params["scales"].shape == (5, 3) and torch.isfinite(params["scales"]).all()
