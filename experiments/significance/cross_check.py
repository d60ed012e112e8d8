"""Does the end-of-run cut's check see what the cut costs on views it was not fitted to? The check
as shipped against a leave-one-view-out check, on a finished run's uncut set (a run trained with
``--strategy.final-weight-share 0``, or resumed that way from a checkpoint before its last step).

As shipped (``DefaultStrategy._checked_cut``), the rows are ordered by their weights over every
training view, and the 24 checked views (``count_rule.evenly_spread``) are among those views: a row
that matters to a checked view has weight there, so the check seldom cuts it. The leave-one-out
check renders each checked view without the rows that a cut ordered by the weights of every
*other* training view takes, so each checked view plays the part of a view the ranking never saw
(as a test view is), with the ranking's information otherwise whole; the rows no other view draws
are checked too, then each share in turn. The share it passes is then cut in the order of every
view's weights, as the shipped cut does. For both rules: the shares tried with the checked views'
paired deficit (``count_rule.paired_deficit``, mean + standard error), and the kept set's count, test
PSNR and LPIPS beside the uncut set's (``cut_criteria.scored``). No fine-tuning.

    python experiments/significance/cross_check.py RUN_DIR [RUN_DIR ...]
"""

from __future__ import annotations

import argparse

import torch

from cut_criteria import scored
from exploregs_plugin.model.significance import VIEW_WEIGHT, add_view_, visibility_cut_order, visibility_totals
from exploregs_plugin.rasterizer.settings import VISIBILITY_COLUMNS
from exploregs_plugin.runs.load import load_run
from exploregs_plugin.strategies.count_rule import CHECK_VIEWS, evenly_spread, paired_deficit
from exploregs_plugin.strategies.default import CHECKED_SHARES
from exploregs_plugin.strategies.significance_prune import least_significant

# the shipped final_weight_share and final_cut_tolerance (the run given has its cut off)
SHARE = 0.003
TOLERANCE = 0.1


def combined(per_view: torch.Tensor, views: list[int]) -> torch.Tensor:
    """[N, 4] of ``views`` taken together as the cut takes views together (``add_view_``: the
    weight and alpha sums added, the peak the largest, the view weight the largest view's weight)."""
    total = torch.zeros_like(per_view[views[0]])
    for view in views:
        add_view_(total, per_view[view][:, :VIEW_WEIGHT])
    return total


def share_rows(totals: torch.Tensor, share: float | None) -> torch.Tensor:
    """[N] bool: the rows no view of ``totals`` draws (no alpha, as ``DefaultStrategy.final_cut``
    reads it), and (``share`` not None) those a cut at ``share`` takes in the cut's order
    (``visibility_cut_order``)."""
    undrawn = totals[:, VISIBILITY_COLUMNS.index("alpha")] <= 0.0
    if share is None:
        return undrawn
    weights = totals[:, 0]
    return undrawn | least_significant(weights, torch.ones_like(weights), share, visibility_cut_order(totals))


def checked_share(deficit, check_undrawn: bool) -> tuple[float | None, list[str]]:
    """The largest share that the checked views miss by at most TOLERANCE (``deficit(share)``, None
    for the rows no view draws), searched as the shipped cut searches; None where even the rows no
    view draws cost more (``check_undrawn``: the shipped cut takes those without a check)."""
    tried, kept = [], 0.0
    if check_undrawn:
        lost = deficit(None)
        tried.append(f"undrawn: {lost:.3f}")
        if not lost <= TOLERANCE:
            return None, tried
    for share in [SHARE] + [q for q in CHECKED_SHARES if q > SHARE]:
        lost = deficit(share)
        tried.append(f"{share:.1%}: {lost:.3f}")
        if not lost <= TOLERANCE:
            break
        kept = share
    return kept, tried


def main(path: str) -> None:
    torch.set_num_threads(1)
    run = load_run(path, "cpu")
    pipeline = run.pipeline
    params = {k: v.detach() for k, v in pipeline.params.items()}
    cameras = pipeline.datamanager.train_cameras
    per_view = torch.stack([visibility_totals(params, [camera], pipeline.model.config.raster, pipeline.background)
                            for camera in cameras])
    views = list(range(len(cameras)))
    every = combined(per_view, views)
    checked = evenly_spread(len(cameras), CHECK_VIEWS)
    without_view = {v: combined(per_view, [u for u in views if u != v]) for v in checked}
    last = pipeline.schedule.max_steps - 1
    base = pipeline.view_psnrs(checked, last)

    def shipped(share: float | None) -> float:
        return paired_deficit(base, pipeline.view_psnrs(checked, last, without=share_rows(every, share)))

    def left_out(share: float | None) -> float:
        return paired_deficit(base, [pipeline.view_psnrs([v], last, without=share_rows(without_view[v], share))[0]
                                     for v in checked])

    count = params["means"].shape[0]
    print(f"{path}: {len(cameras)} training views, {len(checked)} checked, {count:,} Gaussians")
    _, psnr, lpips = scored(run, torch.zeros(count, dtype=torch.bool))[:3]
    print(f"  uncut: test {psnr:.3f} dB, LPIPS {lpips:.4f}", flush=True)
    for name, deficit, check_undrawn in (("shipped", shipped, False), ("leave-one-out", left_out, True)):
        share, tried = checked_share(deficit, check_undrawn)
        kept, psnr, lpips = scored(run, share_rows(every, share or None))[:3]
        print(f"  {name}: share {share} ({'; '.join(tried)}): {kept:,} Gaussians, test {psnr:.3f} dB, "
              f"LPIPS {lpips:.4f}", flush=True)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", help="finished run folders holding the uncut set")
    for run_dir in parser.parse_args().runs:
        main(run_dir)
