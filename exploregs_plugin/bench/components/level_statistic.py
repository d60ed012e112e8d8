"""Default's densification statistic of one Gaussian set rendered at each coarse-to-fine level.

    python -m exploregs_plugin.bench.components.level_statistic RUN_OR_CHECKPOINT [--downscales 2 4]

Renders every training view of a run's checkpoint at full size and at each downscale s (the
views ``DataManager.train_item(i, None, s)`` serves a coarse-to-fine level), back-propagates the
run's own loss, and accumulates Default's statistic as training does (``accumulate_grad_stats``),
once undivided (s = 1 passed for the NDC conversion) and once as training forms it at the level
(divided by s). Prints, per level, the per-Gaussian ratio to full size (median and quartiles over
the Gaussians seen at both) and the share of Gaussians above ``grow_grad2d``. The derivation the
numbers check is in docs/training.md ("Coarse to fine"): undivided, the ratio lies between 1
(Gaussians of many pixels) and s (Gaussians of about one pixel).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from exploregs_plugin.engine.loss_terms import ViewLossInput, view_loss
from exploregs_plugin.runs.load import load_run
from exploregs_plugin.strategies.default import accumulate_grad_stats
from exploregs_plugin.strategies.observation import observe_render


def level_statistics(path: Path, downscales: tuple[int, ...]) -> dict[int, tuple[torch.Tensor, torch.Tensor, int]]:
    """downscale -> (undivided statistic [N], seen [N] bool, image height) over all training views."""
    pipeline = load_run(path, device="cpu").pipeline
    dm, model = pipeline.datamanager, pipeline.model
    out = {}
    for s in (1, *downscales):
        stats: dict[str, torch.Tensor] = {}
        height = 0
        for i in range(len(dm.train_cameras)):
            camera, target, extras = dm.train_item(i, None, s)
            image, _, depth, info = model.render(camera, model.config.sh_degree, pipeline.background)
            view = observe_render(info)
            view.keep_gradient("level_statistic")
            loss, _ = view_loss(pipeline.loss_terms, ViewLossInput(image, target, depth, extras, i))
            loss.backward()
            accumulate_grad_stats(stats, view.screen_gradient(), view.visible(), view.width, view.height)
            for tensor in pipeline.params.values():
                tensor.grad = None
            height = camera.height
        out[s] = (stats["grad2d"] / stats["count"].clamp_min(1.0), stats["count"] > 0, height)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("run", type=Path, help="a run folder (its newest checkpoint) or a checkpoint file")
    parser.add_argument("--downscales", type=int, nargs="+", default=[2, 4])
    parser.add_argument("--threshold", type=float, default=0.0002, help="Default's grow_grad2d")
    args = parser.parse_args()
    result = level_statistics(args.run, tuple(args.downscales))
    full, seen_full, height = result[1]
    print(f"full size: {height} px high, {int(seen_full.sum())} Gaussians seen, "
          f"{100 * float((full[seen_full] > args.threshold).float().mean()):.1f}% above {args.threshold:g}")
    for s in args.downscales:
        stat, seen, h = result[s]
        both = seen & seen_full & (full > 0)
        ratio = stat[both] / full[both]
        above = 100 * float((stat[both] > args.threshold).float().mean())
        above_divided = 100 * float((stat[both] / s > args.threshold).float().mean())
        print(f"downscale {s} ({h} px high): undivided / full median {float(ratio.median()):.2f} "
              f"(quartiles {float(ratio.quantile(0.25)):.2f}-{float(ratio.quantile(0.75)):.2f}); "
              f"above {args.threshold:g}: {above:.1f}% undivided, {above_divided:.1f}% divided by {s}")


if __name__ == "__main__":
    main()
