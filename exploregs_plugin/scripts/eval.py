"""eg-eval: re-evaluate a trained run on its test views.

Writes RUN/eval-step-XXXXXXX/metrics.json and render | ground truth | error PNGs; the
run's own metrics.json is left untouched.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import tyro

from exploregs_plugin.evaluation import evaluate, write_metrics_json
from exploregs_plugin.runs import load_run
from exploregs_plugin.scripts import run_cli


@dataclass
class EvalArgs:
    path: tyro.conf.Positional[Path]
    """A run folder (uses its latest checkpoint) or a checkpoint file."""
    out: Path | None = None
    """Output folder (default: RUN/eval-step-XXXXXXX)."""
    save_images: bool = True
    """Save render | ground truth | error map PNGs."""


def main(args: EvalArgs) -> dict:
    run = load_run(args.path)
    out = args.out or run.run_dir / f"eval-step-{run.step:07d}"
    metrics = evaluate(run.pipeline.model, run.pipeline.datamanager, save_dir=out if args.save_images else None)
    metrics.update({"method": run.config.method_name, "scene": run.pipeline.datamanager.scene_name,
                    "step": run.step, "checkpoint": str(run.checkpoint)})
    write_metrics_json(out / "metrics.json", metrics)
    print(f"PSNR {metrics['psnr']:.3f} dB  SSIM {metrics['ssim']:.4f}  "
          f"{metrics['num_gaussians']} Gaussians  -> {out / 'metrics.json'}")
    return metrics


def entrypoint() -> None:
    run_cli("eg-eval", main, tyro.cli(EvalArgs, description="Re-evaluate a trained ExploreGS run."))


if __name__ == "__main__":
    entrypoint()
