"""The initial scales' nearest neighbours, by the grid against every pair, in one run (the ratio is
what to read: machines are shared and noisy).

    python -m exploregs_plugin.bench.components.neighbours                  # 20k and 60k points
    python -m exploregs_plugin.bench.components.neighbours --points 100000 --threads 2

The cloud is what SfM leaves: points on a noisy sphere (a surface, not a volume) and a few isolated
ones far out. Each size is timed by both paths alternately, ``--rounds`` times; each round's CPU
time of the call is reported, and whether the two gave the same bits.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass

import torch

from exploregs_plugin.model.neighbours import every_pair_mean_distance, knn_mean_distance


@dataclass(frozen=True)
class NeighbourTiming:
    points: int
    grid_s: list[float]
    """Per round: CPU seconds of ``knn_mean_distance``."""
    every_pair_s: list[float]
    """Per round: CPU seconds of every pair (the path below ``BRUTE_FORCE_BELOW`` points)."""
    same_bits: bool


def surface_cloud(points: int, seed: int = 0) -> torch.Tensor:
    """``points`` points: 99% on a sphere of radius 1 with 1% noise in the radius, 1% far out."""
    gen = torch.Generator().manual_seed(seed)
    on_surface = points - points // 100
    u = torch.randn(on_surface, 3, generator=gen)
    sphere = u / u.norm(dim=1, keepdim=True) * (1 + 0.01 * torch.rand(on_surface, 1, generator=gen))
    return torch.cat([sphere, torch.randn(points // 100, 3, generator=gen) * 20])


def time_neighbours(points: int, threads: int = 1, rounds: int = 2) -> NeighbourTiming:
    cloud = surface_cloud(points)
    previous = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        grid, brute, same = [], [], True
        for _ in range(rounds):
            start = time.process_time()
            by_grid = knn_mean_distance(cloud)
            grid.append(time.process_time() - start)
            start = time.process_time()
            by_pairs = every_pair_mean_distance(cloud)
            brute.append(time.process_time() - start)
            same = same and torch.equal(by_grid, by_pairs)
    finally:
        torch.set_num_threads(previous)
    return NeighbourTiming(points, grid, brute, same)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, nargs="+", default=[20_000, 60_000])
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--rounds", type=int, default=2)
    args = parser.parse_args(argv)
    print(f"# mean distance to the 3 nearest points, surface cloud, {args.threads} thread(s), CPU seconds per call")
    print("| points | round | grid (s) | every pair (s) | grid / every pair | same bits |")
    print("|---|---|---|---|---|---|")
    for n in args.points:
        t = time_neighbours(n, args.threads, args.rounds)
        for i, (g, b) in enumerate(zip(t.grid_s, t.every_pair_s)):
            print(f"| {n} | {i + 1} | {g:.2f} | {b:.2f} | {g / b:.3f}x | {t.same_bits} |")


if __name__ == "__main__":
    main()
