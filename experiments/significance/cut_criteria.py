"""Which Gaussians can a finished run lose? Cut criteria compared on one run, no fine-tuning.

For a trained run: each Gaussian's compositing weight S = sum alpha T, its alpha sum A, its peak
P = max alpha T and its view weight W = max_views S(view) over every training view (one pass, SH
degree 0), then the set cut by
- ``share q``: the end-of-run cut's rule: every row no view drew (A = 0), then in the order of
  W x P (``visibility_cut_order``) the rows whose S adds up to at most q of the total; ``share q by
  S x P``: the order before 2026-12-07, and the same count in the order W x P; ``share q by S``: the
  same in the order of S; ``before the peak``: the default before 2026-11-29's peak (share 0.001
  in the order of S, the undrawn rows kept),
- ``kept f``: the fraction f of the rows with the largest W x P (the choice of ``eg-export
  --max-gaussians``), and with the largest S,
- ``hidden t``: rows whose mean transmittance S / A is below t (drawn, but behind others),
each scored on the test views (PSNR, LPIPS, and the PSNR of each labelled region, such as the
built-in scenes' far region) against the whole set.

    python experiments/significance/cut_criteria.py RUN_DIR [RUN_DIR ...]
    python experiments/significance/cut_criteria.py RUN_DIR --shares 0.003 0.01 --fractions 0.67 0.5 --no-hidden
"""

from __future__ import annotations

import argparse
import copy

import torch

from exploregs_plugin.evaluation.metrics import evaluate
from exploregs_plugin.model.significance import cut_order, most_significant, visibility_cut_order, visibility_totals
from exploregs_plugin.rasterizer.settings import VISIBILITY_PEAK
from exploregs_plugin.runs.load import load_run
from exploregs_plugin.strategies import row_ops
from exploregs_plugin.strategies.significance_prune import least_significant


def weight_sums(pipeline) -> torch.Tensor:
    """[N, 4] float64 over every training view: S, A, P, W (``CUT_COLUMNS``)."""
    params = {k: v.detach() for k, v in pipeline.params.items()}
    return visibility_totals(params, pipeline.datamanager.train_cameras, pipeline.model.config.raster,
                             pipeline.background)


def scored(run, mask: torch.Tensor) -> tuple[int, float, float, dict[str, float]]:
    """(Gaussians kept, test PSNR, LPIPS, PSNR per labelled region: far, occluded, ... where the
    scene has region masks) of the run's set without the rows of ``mask``."""
    pipeline = run.pipeline
    saved = copy.deepcopy(pipeline.state_dict())
    row_ops.remove(pipeline.params, pipeline.optimizers, {}, mask)
    m = evaluate(pipeline.model, pipeline.datamanager)
    pipeline.load_state_dict(saved)
    regions = {k: round(v, 3) for k, v in (m.get("region_psnr") or {}).items()}
    return int((~mask).sum()), round(m["psnr"], 4), round(m.get("lpips") or float("nan"), 5), regions


def main(path: str, shares: tuple[float, ...] = (0.001, 0.003, 0.01), fractions: tuple[float, ...] = (),
         hidden: bool = True) -> None:
    run = load_run(path, "cpu")
    totals = weight_sums(run.pipeline)
    s, a = totals[:, 0], totals[:, 1]
    n = s.shape[0]
    every = torch.ones(n, dtype=torch.float64)
    print(f"{path}: {n} Gaussians, {int((a == 0).sum())} drawn by no training view")
    print("whole", scored(run, torch.zeros(n, dtype=torch.bool)), flush=True)
    print("undrawn", scored(run, a == 0), flush=True)
    print("before the peak", scored(run, least_significant(s, a, 0.001)), flush=True)
    order = visibility_cut_order(totals)  # the cuts' order: W x P
    summed_order = cut_order(s, totals[:, VISIBILITY_PEAK])  # the cuts' order before 2026-12-07: S x P
    for q in shares:
        print(f"share {q}", scored(run, least_significant(s, every, q, order)), flush=True)
        print(f"share {q} by S", scored(run, least_significant(s, every, q)), flush=True)
        by_sum = least_significant(s, every, q, summed_order) | (a == 0)
        print(f"share {q} by S x P", scored(run, by_sum), flush=True)
        # the same count in the cuts' order, W x P: which rows, not how many
        keep = most_significant(torch.where(a == 0, -1.0, order), n - int(by_sum.sum()))
        print(f"  its count by W x P", scored(run, ~keep), flush=True)
    for f in fractions:
        count = max(1, int(f * n))
        print(f"kept {f}", scored(run, ~most_significant(order, count)), flush=True)
        print(f"kept {f} by S", scored(run, ~most_significant(s, count)), flush=True)
    if not hidden:
        return
    t_mean = s / a.clamp_min(1e-12)
    for t in (0.02, 0.05, 0.1, 0.2):
        print(f"hidden {t}", scored(run, (a > 0) & (t_mean < t)), flush=True)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", help="finished run folders")
    parser.add_argument("--shares", type=float, nargs="*", default=[0.001, 0.003, 0.01])
    parser.add_argument("--fractions", type=float, nargs="*", default=[], help="fractions of the rows kept")
    parser.add_argument("--no-hidden", action="store_true", help="skip the mean-transmittance criterion")
    args = parser.parse_args()
    for run_dir in args.runs:
        main(run_dir, tuple(args.shares), tuple(args.fractions), not args.no_hidden)
