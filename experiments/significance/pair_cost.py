"""What a cut saves of a training step: a checkpoint's set against the same set cut to KEEP rows,
kept in the cuts' order (W x P, model/significance.py) and in that order divided by each row's
footprint (W x P / A^a, A the row's screen area summed over the training views), with for each:
the tile-Gaussian pairs summed over the training views (what the compiled compositing loops over),
the CPU seconds of a forward and backward render of every training view on one thread, and the
paired deficit on the cut's 24 checked training views (strategies/count_rule.py).

    python experiments/significance/pair_cost.py RUN_DIR/checkpoints/step-0001000.pt 11953
"""

from __future__ import annotations

import argparse
import time

import torch

from exploregs_plugin.engine import count_trial
from exploregs_plugin.model.gaussians import render_params
from exploregs_plugin.model.significance import visibility_cut_order
from exploregs_plugin.runs.load import load_run
from exploregs_plugin.strategies.count_rule import CHECK_VIEWS, evenly_spread, paired_deficit


def pairs_and_area(pipeline, params) -> tuple[int, torch.Tensor]:
    """The tile-Gaussian pairs over the training views, and each row's summed screen area
    ((2 r + 1)^2 pixels of its radius r where the view draws it)."""
    area = torch.zeros(params["means"].shape[0], dtype=torch.float64)
    pairs = 0
    settings = pipeline.model.config.raster
    with torch.no_grad():
        for index in range(len(pipeline.datamanager.train_cameras)):
            camera, _, _ = pipeline.datamanager.train_item(index, pipeline.device)
            info = render_params(params, camera, 3, pipeline.background, settings)[3]
            pairs += int(info["n_pairs"])
            radius = info["radii"].to(torch.float64)
            radius = radius.max(dim=-1).values if radius.dim() > 1 else radius
            area += torch.where(info["visible"], (2.0 * radius + 1.0) ** 2, 0.0)
    return pairs, area


def render_seconds(pipeline, params) -> float:
    """CPU seconds of a forward and backward render of every training view (one thread)."""
    leaves = {k: v.clone().requires_grad_(True) for k, v in params.items()}
    start = time.process_time()
    for index in range(len(pipeline.datamanager.train_cameras)):
        camera, target, _ = pipeline.datamanager.train_item(index, pipeline.device)
        image = render_params(leaves, camera, 3, pipeline.background, pipeline.model.config.raster)[0]
        ((image - target) ** 2).mean().backward()
    return time.process_time() - start


def main(checkpoint: str, keep: int, exponents: list[float]) -> None:
    torch.set_num_threads(1)
    run = load_run(checkpoint, "cpu")
    pipeline, step = run.pipeline, run.step
    full = {k: v.detach() for k, v in pipeline.params.items()}
    n = full["means"].shape[0]
    checked = evenly_spread(len(pipeline.datamanager.train_cameras), CHECK_VIEWS)
    base = pipeline.view_psnrs(checked, step)
    pairs, area = pairs_and_area(pipeline, full)
    print(f"step {step}, the whole set: {n:,} rows, {pairs:,} pairs, {render_seconds(pipeline, full):.2f} s", flush=True)
    score = visibility_cut_order(count_trial.training_visibility(pipeline))
    for exponent in exponents:
        order = torch.sort(score / area.clamp_min(1.0) ** exponent, descending=True, stable=True).indices
        kept = torch.zeros(n, dtype=torch.bool)
        kept[order[:keep]] = True
        params = {k: v[kept] for k, v in full.items()}
        cut_pairs = pairs_and_area(pipeline, params)[0]
        deficit = paired_deficit(base, pipeline.view_psnrs(checked, step, without=~kept))
        print(f"W x P / A^{exponent:g}, {keep:,} kept: {cut_pairs:,} pairs ({cut_pairs / pairs:.0%}), "
              f"{render_seconds(pipeline, params):.2f} s, the checked views lose {deficit:.3f} dB", flush=True)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoint", help="a checkpoint file (or a run folder: its latest)")
    parser.add_argument("keep", type=int, help="rows to keep")
    parser.add_argument("--exponents", type=float, nargs="+", default=[0.0, 0.5, 1.0])
    args = parser.parse_args()
    main(args.checkpoint, args.keep, args.exponents)
