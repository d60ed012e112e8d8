"""What the cut's shares cost on a checkpoint's set, with no training after the cut: the check's
paired PSNR deficit of its 24 training views, their mean SSIM deficit, and the test views' PSNR and
LPIPS changes (the cut's order, weight x peak over every training view, as the cuts take it).

    python experiments/significance/cut_ssim.py RUN_DIR/checkpoints/step-0001000.pt
"""

from __future__ import annotations

import argparse
import statistics

import torch

from exploregs_plugin.engine import count_trial
from exploregs_plugin.evaluation.perceptual import lpips_network
from exploregs_plugin.model.gaussians import render_params
from exploregs_plugin.model.losses import psnr, ssim
from exploregs_plugin.model.significance import visibility_cut_order
from exploregs_plugin.runs.load import load_run
from exploregs_plugin.strategies.count_rule import CHECK_VIEWS, evenly_spread, paired_deficit
from exploregs_plugin.strategies.significance_prune import least_significant


def renders(pipeline, params, items) -> list[tuple[float, float, torch.Tensor, torch.Tensor]]:
    """(PSNR, SSIM, image, target) of each (camera, target) of ``items``."""
    out = []
    with torch.no_grad():
        for camera, target in items:
            image = render_params(params, camera, 3, pipeline.background, pipeline.model.config.raster)[0].clamp(0, 1)
            out.append((psnr(image, target), float(ssim(image, target)), image, target))
    return out


def main(checkpoint: str, shares: list[float]) -> None:
    torch.set_num_threads(1)
    pipeline = load_run(checkpoint, "cpu").pipeline
    full = {k: v.detach() for k, v in pipeline.params.items()}
    visibility = count_trial.training_visibility(pipeline)
    order = visibility_cut_order(visibility)
    dm = pipeline.datamanager
    checked = [dm.train_item(i, pipeline.device)[:2] for i in evenly_spread(len(dm.train_cameras), CHECK_VIEWS)]
    tests = [dm.test_item(i, pipeline.device)[:2] for i in range(len(dm.test_cameras))]
    net = lpips_network("cpu")
    base_checked, base_test = renders(pipeline, full, checked), renders(pipeline, full, tests)
    base_lpips = statistics.mean(net.distance(r[2], r[3]) for r in base_test)
    base_psnr = statistics.mean(r[0] for r in base_test)
    print(f"the whole set: {full['means'].shape[0]:,} Gaussians; test PSNR {base_psnr:.3f}, LPIPS {base_lpips:.4f}")
    for share in shares:
        cut = least_significant(visibility[:, 0], torch.ones_like(visibility[:, 0]), share, order)
        cut |= visibility[:, 1] <= 0.0  # the rows no training view draws go first, as in the cuts
        params = {k: v[~cut] for k, v in full.items()}
        after_checked, after_test = renders(pipeline, params, checked), renders(pipeline, params, tests)
        deficit = paired_deficit([r[0] for r in base_checked], [r[0] for r in after_checked])
        ssim_lost = statistics.mean(b[1] - a[1] for b, a in zip(base_checked, after_checked))
        lpips = statistics.mean(net.distance(r[2], r[3]) for r in after_test)
        print(f"share {share:.1%}: {int((~cut).sum()):,} kept; the checked views lose {deficit:.3f} dB and "
              f"{ssim_lost:.4f} SSIM; the test views {statistics.mean(r[0] for r in after_test) - base_psnr:+.3f} dB, "
              f"LPIPS {lpips - base_lpips:+.4f}", flush=True)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoint", help="a checkpoint file (or a run folder: its latest)")
    parser.add_argument("--shares", type=float, nargs="+", default=[0.003, 0.005, 0.01, 0.02, 0.03])
    args = parser.parse_args()
    main(args.checkpoint, args.shares)
