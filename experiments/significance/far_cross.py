"""The far region scored on every run's masks: groups of runs of one scene (for example one tree's
seeds and another's), each run's final model on the far masks (the bench's rule,
``exploregs_plugin.bench.far_region``) of every other run. A run mostly scores higher on its own
masks, so a comparison on one group's masks leans towards that group; here each run's masks judge
all the others, its own run left out.

    python experiments/significance/far_cross.py d015=RUN_A0,RUN_A1 today=RUN_B0,RUN_B1 [--quantile 0.75] [--matrix]

Prints, per mask source, each group's mean far-region PSNR (its own run left out), and for each
group against the first: the mean difference over the mask sources and its standard deviation.
``--matrix`` also prints every run on every run's masks, its own included (for one run a group).
"""

from __future__ import annotations

import argparse
import math
import statistics
from pathlib import Path

import torch

from exploregs_plugin.bench.far_region import FAR_QUANTILE, _load_final, _test_views, far_mask, masked_squared_error
from exploregs_plugin.model.losses import pooled_psnr


def rendered(run_dir: Path, quantile: float) -> tuple[list[tuple[torch.Tensor, torch.Tensor]], list[torch.Tensor]]:
    """A run's (image, target) per test view and its own far masks."""
    views, masks = [], []
    for _, target, image, alpha, depth in _test_views(_load_final(run_dir, "cpu")):
        views.append((image, target))
        masks.append(far_mask(alpha, depth, quantile))
    return views, masks


def far_psnr(views: list[tuple[torch.Tensor, torch.Tensor]], masks: list[torch.Tensor]) -> float:
    """Pooled PSNR over all test views' masked pixels (as far_region_psnr pools them)."""
    total, count = 0.0, 0
    for (image, target), mask in zip(views, masks):
        sq, n = masked_squared_error(image, target, mask)
        total, count = total + sq, count + n
    return pooled_psnr(total, count)


def main(groups: dict[str, list[Path]], quantile: float, matrix: bool = False) -> None:
    torch.set_num_threads(1)
    runs = {run: rendered(run, quantile) for paths in groups.values() for run in paths}
    names = list(groups)
    if matrix:  # every run on every run's masks, its own included
        for source, (_, masks) in runs.items():
            print(f"on {source}'s masks: " + ", ".join(f"{run} {far_psnr(views, masks):.3f}"
                                                       for run, (views, _) in runs.items()))
    print("mask source: " + " | ".join(names))
    diffs: dict[str, list[float]] = {name: [] for name in names[1:]}
    for source, (_, masks) in runs.items():
        # a group whose only run is the mask's source has no value on these masks (NaN)
        means = {name: statistics.mean([far_psnr(runs[r][0], masks) for r in paths if r != source] or [math.nan])
                 for name, paths in groups.items()}
        print(f"{source}: " + " | ".join(f"{means[n]:.3f}" for n in names), flush=True)
        for name in names[1:]:
            if not math.isnan(means[name] - means[names[0]]):
                diffs[name].append(means[name] - means[names[0]])
    for name, values in diffs.items():
        spread = f" (sd {statistics.stdev(values):.3f})" if len(values) > 1 else ""
        print(f"{name} - {names[0]}: {statistics.mean(values):+.3f} dB over {len(values)} mask sources{spread}"
              if values else f"{name} - {names[0]}: no mask source scores both")


def _group(text: str) -> tuple[str, list[Path]]:
    name, _, paths = text.partition("=")
    if not name or not paths:
        raise argparse.ArgumentTypeError(f"expected NAME=RUN,RUN,...; got {text!r}")
    return name, [Path(p) for p in paths.split(",")]


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("groups", nargs="+", type=_group, help="NAME=RUN,RUN,... (the first group is the reference)")
    parser.add_argument("--quantile", type=float, default=FAR_QUANTILE)
    parser.add_argument("--matrix", action="store_true", help="also every run on every run's masks, its own included")
    args = parser.parse_args()
    main(dict(args.groups), args.quantile, args.matrix)
