"""The initial Gaussians' scales: the mean distance to the 3 nearest points, wherever the cloud lies."""

from __future__ import annotations

import pytest
import torch

from exploregs_plugin.model.gaussians import init_params, knn_mean_distance
from exploregs_plugin.model.neighbours import every_pair_mean_distance


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


def _hard_cloud(offset: float, n: int = 6000) -> torch.Tensor:
    """About 2.1 n points as SfM leaves them: a noisy sphere and a plane (surfaces, not a volume),
    isolated points far out and a little off the sphere, exact twins and a straight line, at
    ``offset`` from the origin."""
    g = torch.Generator().manual_seed(3)
    u = torch.randn(n, 3, generator=g)
    sphere = u / u.norm(dim=1, keepdim=True) + 0.002 * torch.randn(n, 3, generator=g)
    plane = torch.cat([torch.rand(2 * n // 3, 2, generator=g) * 4 - 2, torch.full((2 * n // 3, 1), -1.0)], dim=1)
    far = torch.randn(n // 60, 3, generator=g) * 30
    v = torch.randn(n // 60, 3, generator=g)  # a little off the sphere, alone among its cells
    satellites = v / v.norm(dim=1, keepdim=True) * (1.1 + 0.2 * torch.rand(n // 60, 1, generator=g))
    line = torch.cat([torch.linspace(2, 3, n // 3)[:, None], torch.zeros(n // 3, 2)], dim=1)
    twins = sphere[: n // 10].clone()
    return torch.cat([sphere, plane, far, satellites, line, twins]) + offset


@pytest.mark.parametrize("offset", [0.0, 1.0e4])
def test_the_grid_finds_the_same_neighbours_as_every_pair_bit_for_bit(offset, monkeypatch):
    """Above BRUTE_FORCE_BELOW points the neighbours come from a grid: the same bits as every
    pair, at one and two threads, on a cloud near the origin and far from it (the threshold
    lowered, so that every pair, the reference, is a quarter of its cost at the real one)."""
    from exploregs_plugin.model import neighbours

    monkeypatch.setattr(neighbours, "BRUTE_FORCE_BELOW", 2000)
    points = _hard_cloud(offset, n=3000)
    assert points.shape[0] > neighbours.BRUTE_FORCE_BELOW
    every_pair = every_pair_mean_distance(points)
    before = torch.get_num_threads()
    try:
        for threads in (1, 2):
            torch.set_num_threads(threads)
            assert torch.equal(knn_mean_distance(points), every_pair)
    finally:
        torch.set_num_threads(before)
    twins = 3000 // 10  # the cloud's last rows: copies of its first sphere points
    assert (every_pair[-twins:] == every_pair[:twins]).all() and (every_pair[:twins] > 0).all()


def test_points_left_uncertain_by_a_grid_go_round_again_with_coarser_ones(monkeypatch):
    """With small query blocks the isolated points' neighbours may lie beyond the cells searched:
    they are searched again in grids of twice the cell, then by every pair, and still end with the
    bits of every pair."""
    from exploregs_plugin.model import neighbours

    monkeypatch.setattr(neighbours, "BRUTE_FORCE_BELOW", 500)
    monkeypatch.setattr(neighbours, "CHUNK_POINTS", 16)
    monkeypatch.setattr(neighbours, "BRUTE_FORCE_ROWS", 8)
    rounds: list[tuple[int, float]] = []
    real = neighbours._nearest_in_grid
    monkeypatch.setattr(neighbours, "_nearest_in_grid",
                        lambda p, pending, cell, k: rounds.append((pending.numel(), cell)) or real(p, pending, cell, k))
    points = _hard_cloud(0.0, n=1500)
    assert torch.equal(knn_mean_distance(points), every_pair_mean_distance(points))
    assert len(rounds) >= 3 and rounds[0][0] == points.shape[0] - neighbours.SAMPLE_POINTS  # the sample is final
    assert all(b[0] <= a[0] and b[1] == 2 * a[1] for a, b in zip(rounds, rounds[1:])) and rounds[1][0] < rounds[0][0]
