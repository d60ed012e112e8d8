"""Do training views see what a cut costs? The per-view PSNR a finished run's training views lose
to larger end-of-run cuts, paired against the set as it ended, beside the test views' loss.

For each run: the end-of-run cut's order (weight x peak over every training view), then the set
cut at each share of the blend weight and to fractions of its rows; for each cut, over every
training view, d_v = PSNR of the whole set - PSNR of the cut set, printed as mean(d), sd(d) /
sqrt(k) and max(d) (the check of ``final_cut_tolerance`` reads mean + sd / sqrt(k) over 24 of these
views), and the test views' PSNR and LPIPS (``cut_criteria.scored``). No fine-tuning.

    python experiments/significance/train_deficit.py RUN_DIR [RUN_DIR ...]
    python experiments/significance/train_deficit.py RUN_DIR --shares 0.005 0.01 --fractions 0.5 --no-test
"""

from __future__ import annotations

import argparse
import math

import torch

from cut_criteria import scored, weight_sums
from exploregs_plugin.model.significance import most_significant, visibility_cut_order
from exploregs_plugin.runs.load import load_run
from exploregs_plugin.strategies.significance_prune import least_significant


def main(path: str, shares: tuple[float, ...], fractions: tuple[float, ...], test: bool) -> None:
    run = load_run(path, "cpu")
    pipeline = run.pipeline
    views = list(range(len(pipeline.datamanager.train_cameras)))
    step = run.step
    totals = weight_sums(pipeline)
    order = visibility_cut_order(totals)
    n = totals.shape[0]
    every = torch.ones(n, dtype=torch.float64)
    whole = torch.tensor(pipeline.view_psnrs(views, step), dtype=torch.float64)
    print(f"{path}: {n} Gaussians, training PSNR {whole.mean():.3f} dB over {len(views)} views", flush=True)
    cuts = [(f"share {q}", least_significant(totals[:, 0], every, q, order)) for q in shares]
    cuts += [(f"kept {f}", ~most_significant(order, max(1, int(f * n)))) for f in fractions]
    for name, mask in cuts:
        d = whole - torch.tensor(pipeline.view_psnrs(views, step, without=mask), dtype=torch.float64)
        line = (f"  {name}: {int((~mask).sum())} kept ({float((~mask).sum()) / n:.2f}); training views lose "
                f"{d.mean():.3f} dB, sd/sqrt(k) {d.std() / math.sqrt(len(d)):.3f}, max {d.max():.3f}")
        if test:
            line += f"; test (kept, PSNR, LPIPS, regions) {scored(run, mask)}"
        print(line, flush=True)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", help="finished run folders")
    parser.add_argument("--shares", type=float, nargs="*", default=[0.005, 0.01, 0.02, 0.03])
    parser.add_argument("--fractions", type=float, nargs="*", default=[0.7, 0.5], help="fractions of the rows kept")
    parser.add_argument("--no-test", action="store_true", help="training views only")
    args = parser.parse_args()
    for run_dir in args.runs:
        main(run_dir, tuple(args.shares), tuple(args.fractions), not args.no_test)
