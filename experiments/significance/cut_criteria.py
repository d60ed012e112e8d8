"""Which Gaussians can a finished run lose? Cut criteria compared on one run, no fine-tuning.

For a trained run: each Gaussian's compositing weight S = sum alpha T and its alpha sum A over every
training view (one pass, SH degree 0), then the set cut by
- ``share``: the least significant rows whose S adds up to at most q of the total (the significance
  prune's rule, here with the weights of every training view),
- ``hidden``: rows whose mean transmittance S / A is below t (drawn, but behind others),
each scored on the test views (PSNR, LPIPS, and the PSNR of each labelled region, such as the
built-in scenes' far region) against the whole set.

    python experiments/significance/cut_criteria.py RUN_DIR [RUN_DIR ...]
    python experiments/significance/cut_criteria.py RUN_DIR --shares 0.003 0.01 0.02 0.04 --no-hidden
"""

from __future__ import annotations

import argparse
import copy

import torch

from exploregs_plugin.evaluation.metrics import evaluate
from exploregs_plugin.model.significance import visibility_totals
from exploregs_plugin.runs.load import load_run
from exploregs_plugin.strategies import row_ops
from exploregs_plugin.strategies.significance_prune import least_significant


def weight_sums(pipeline) -> tuple[torch.Tensor, torch.Tensor]:
    params = {k: v.detach() for k, v in pipeline.params.items()}
    totals = visibility_totals(params, pipeline.datamanager.train_cameras, pipeline.model.config.raster,
                               pipeline.background)
    return totals[:, 0], totals[:, 1]


def scored(run, mask: torch.Tensor) -> tuple[int, float, float, dict[str, float]]:
    """(Gaussians kept, test PSNR, LPIPS, PSNR per labelled region: far, occluded, ... where the
    scene has region masks) of the run's set without the rows of ``mask``."""
    pipeline = run.pipeline
    saved = copy.deepcopy(pipeline.state_dict())
    row_ops.remove(pipeline.params, pipeline.optimizers, {}, mask)
    m = evaluate(pipeline.model, pipeline.datamanager)
    pipeline.load_state_dict(saved)
    regions = {k: round(v, 3) for k, v in (m.get("region_psnr") or {}).items()}
    return int((~mask).sum()), m["psnr"], m.get("lpips") or float("nan"), regions


def main(path: str, shares: tuple[float, ...] = (0.001, 0.003, 0.01), hidden: bool = True) -> None:
    run = load_run(path, "cpu")
    s, a = weight_sums(run.pipeline)
    drawn = (a > 0).float()
    n = s.shape[0]
    print(f"{path}: {n} Gaussians")
    print("whole", scored(run, torch.zeros(n, dtype=torch.bool)), flush=True)
    for q in shares:
        print(f"share {q}", scored(run, least_significant(s, drawn, q)), flush=True)
    if not hidden:
        return
    t_mean = s / a.clamp_min(1e-12)
    for t in (0.02, 0.05, 0.1, 0.2):
        print(f"hidden {t}", scored(run, (a > 0) & (t_mean < t)), flush=True)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", help="finished run folders")
    parser.add_argument("--shares", type=float, nargs="+", default=[0.001, 0.003, 0.01])
    parser.add_argument("--no-hidden", action="store_true", help="skip the mean-transmittance criterion")
    args = parser.parse_args()
    for run_dir in args.runs:
        main(run_dir, tuple(args.shares), not args.no_hidden)
