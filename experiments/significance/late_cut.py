"""A cut before the end of a finished run, then the rest of its steps: what training on recovers.

Loads a run's checkpoint at step K, removes rows by the end-of-run cut's rule (every training
view's weight S and peak P; ``share`` of S in the order of S x P, or of S alone with ``S:``), trains
the remaining steps as the run would (its strategy, schedule and seeds) and scores the test views.
``SP:0`` continues without a cut: it ends with the run's own final scores (a check).

    python experiments/significance/late_cut.py RUN_DIR 1000 1500 SP:0 SP:0.01 S:0.01
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

from exploregs_plugin.engine import count_trial
from exploregs_plugin.evaluation.metrics import evaluate
from exploregs_plugin.model.significance import visibility_cut_order
from exploregs_plugin.runs.load import load_run
from exploregs_plugin.strategies import row_ops
from exploregs_plugin.strategies.significance_prune import least_significant


def late_cut(run_dir: Path, step: int, end: int, order: str, share: float) -> str:
    run = load_run(run_dir / "checkpoints" / f"step-{step:07d}.pt", "cpu")
    pipeline = run.pipeline
    before = pipeline.model.num_gaussians
    if share > 0.0:
        totals = count_trial.training_visibility(pipeline)
        every = torch.ones(totals.shape[0], dtype=torch.float64)
        score = visibility_cut_order(totals) if order == "SP" else None
        cut = least_significant(totals[:, 0], every, share, score)
        row_ops.remove(pipeline.params, pipeline.optimizers, pipeline.strategy_state.get("stats", {}), cut)
    kept = pipeline.model.num_gaussians
    start = time.perf_counter()
    for s in range(run.step, end):
        pipeline.train_step(s)
    seconds = time.perf_counter() - start
    m = evaluate(pipeline.model, pipeline.datamanager)
    return (f"{order}:{share:g} at step {run.step}: {before} -> {kept} Gaussians, {pipeline.model.num_gaussians} at "
            f"{end}: PSNR {m['psnr']:.4f} dB, LPIPS {m['lpips']:.5f}, {seconds:.1f} s for the steps after the cut")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path, help="a finished run folder with a checkpoint at the step")
    parser.add_argument("step", type=int, help="the checkpoint's step")
    parser.add_argument("end", type=int, help="the run's last step + 1 (its --max-steps)")
    parser.add_argument("cuts", nargs="+", help="ORDER:SHARE, ORDER SP (weight x peak) or S (weight)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    for spec in args.cuts:
        order, share = spec.split(":")
        print(late_cut(args.run, args.step, args.end, order, float(share)), flush=True)
