"""What the cut's shares cost on a checkpoint's set, with no training after the cut: the check's
paired PSNR deficit of its 24 training views (``Pipeline.view_psnrs``, as the check reads them),
their mean SSIM deficit, and the test views' PSNR and LPIPS changes (``cut_criteria.scored``: the
evaluation's own); the rows of each share are those the cuts take (``cross_check.share_rows``: the
rows no training view draws, then weight x peak).

    python experiments/significance/cut_ssim.py RUN_DIR/checkpoints/step-0001000.pt
"""

from __future__ import annotations

import argparse
import statistics

import torch

from cross_check import share_rows
from cut_criteria import scored
from exploregs_plugin.engine import count_trial
from exploregs_plugin.model.gaussians import render_params
from exploregs_plugin.model.losses import ssim
from exploregs_plugin.runs.load import load_run
from exploregs_plugin.strategies.count_rule import CHECK_VIEWS, evenly_spread, paired_deficit


def view_ssims(pipeline, indices: list[int], step: int, without: torch.Tensor) -> list[float]:
    """SSIM of each of these training views without the rows of ``without``, rendered as
    ``Pipeline.view_psnrs`` renders them for the check (the step's SH degree)."""
    params = {k: v.detach()[~without] for k, v in pipeline.params.items()}
    out = []
    with torch.no_grad():
        for index in indices:
            camera, target, _ = pipeline.datamanager.train_item(index, pipeline.device)
            image = render_params(params, camera, pipeline.sh_degree_at(step), pipeline.background,
                                  pipeline.model.config.raster)[0]
            out.append(float(ssim(image.clamp(0, 1), target)))
    return out


def main(checkpoint: str, shares: list[float]) -> None:
    torch.set_num_threads(1)
    run = load_run(checkpoint, "cpu")
    pipeline, step = run.pipeline, run.step
    visibility = count_trial.training_visibility(pipeline)
    checked = evenly_spread(len(pipeline.datamanager.train_cameras), CHECK_VIEWS)
    none = torch.zeros(visibility.shape[0], dtype=torch.bool)
    base_psnrs, base_ssims = pipeline.view_psnrs(checked, step), view_ssims(pipeline, checked, step, none)
    _, base_psnr, base_lpips, _ = scored(run, none)
    print(f"the whole set: {visibility.shape[0]:,} Gaussians; test PSNR {base_psnr:.3f}, LPIPS {base_lpips:.4f}")
    for share in shares:
        cut = share_rows(visibility, share)
        deficit = paired_deficit(base_psnrs, pipeline.view_psnrs(checked, step, without=cut))
        ssim_lost = statistics.mean(b - a for b, a in zip(base_ssims, view_ssims(pipeline, checked, step, cut)))
        kept, psnr, lpips, _ = scored(run, cut)
        print(f"share {share:.1%}: {kept:,} kept; the checked views lose {deficit:.3f} dB and {ssim_lost:.4f} SSIM; "
              f"the test views {psnr - base_psnr:+.3f} dB, LPIPS {lpips - base_lpips:+.4f}", flush=True)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoint", help="a checkpoint file (or a run folder: its latest)")
    parser.add_argument("--shares", type=float, nargs="+", default=[0.003, 0.005, 0.01, 0.02, 0.03])
    args = parser.parse_args()
    main(args.checkpoint, args.shares)
