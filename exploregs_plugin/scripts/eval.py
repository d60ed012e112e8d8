"""eg-eval: evaluate a trained run, or a scene file (3DGS PLY, compressed PLY, .splat, .spz), on test views.

    eg-eval RUN_DIR_OR_CHECKPOINT                       # the run's own test views
    eg-eval scene.ply --data DATASET [--data-factor N]  # a PLY (ours or another tool's)

Writes metrics.json and render | ground truth | error PNGs (for a run: RUN/eval-step-XXXXXXX/,
leaving the run's own metrics.json untouched; for a PLY: NAME-eval/ beside it).
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import tyro

from exploregs_plugin.data import DataManagerConfig
from exploregs_plugin.runtime.device import resolve_device
from exploregs_plugin.evaluation.metrics import evaluate, write_metrics_json
from exploregs_plugin.io.checkpoint import check_output_folder
from exploregs_plugin.io.scene_files import read_scene
from exploregs_plugin.rasterizer import backend_line
from exploregs_plugin.runs.scene import dataset_normalization, is_scene_file, model_from_params, scene_file_kind
from exploregs_plugin.runs import load_run
from exploregs_plugin.scripts import parse_cli, run_cli


@dataclass
class EvalArgs:
    path: tyro.conf.Positional[Path]
    """A run folder (uses its latest checkpoint), a checkpoint file, or a scene file (.ply, .compressed.ply,
    .splat, .spz)."""
    out: Path | None = None
    """Output folder (default: RUN/eval-step-XXXXXXX, or NAME-eval/ beside a PLY)."""
    save_images: bool = True
    """Save render | ground truth | error map PNGs."""
    data: str | None = None
    """For a PLY: the dataset whose test views score it (a dataset path or builtin:NAME)."""
    data_factor: int | None = None
    """For a PLY: image downscale factor of --data, as eg-train's --data-factor (unset: 1). A run is
    scored at the factor it trained at."""
    ply_frame: Literal["original", "normalized"] = "original"
    """For a PLY: it holds the dataset's original coordinates (as eg-export writes by default) or
    the normalised training frame."""
    device: str = "auto"
    """Where to compute: auto (CUDA when available, else CPU), cpu, cuda or cuda:N."""


def main(args: EvalArgs) -> dict:
    if args.out is not None:
        check_output_folder("--out", args.out)
    if is_scene_file(args.path):
        if args.data is None:
            raise ValueError(f"{args.path}: a {scene_file_kind(args.path)} holds no cameras or images; pass --data "
                             "DATASET to score it")
        dm = DataManagerConfig(data=args.data, data_factor=args.data_factor or 1).setup()
        scene = read_scene(args.path, dataset_normalization(dm) if args.ply_frame == "original" else None)
        if scene.dropped:
            print(f"{args.path}: left out {scene.dropped} of {scene.dropped + scene.num_gaussians} Gaussians "
                  f"({scene_file_kind(args.path)} rows) with NaN or inf values; scoring the other "
                  f"{scene.num_gaussians}", file=sys.stderr)
        model = model_from_params(scene.params, scene.sh_degree, device=args.device)
        out = args.out or args.path.with_name(args.path.stem + "-eval")
        extra = {"ply": str(args.path), "data": args.data, "dropped_nonfinite": scene.dropped}
    else:
        for flag, value in (("--data", args.data), ("--data-factor", args.data_factor)):
            if value is not None:
                raise ValueError(f"{flag} is for PLY input; {args.path} is a run, scored on the test views of its "
                                 "own dataset at the factor it trained at")
        run = load_run(args.path, args.device)
        model, dm = run.pipeline.model, run.pipeline.datamanager
        out = args.out or run.run_dir / f"eval-step-{run.step:07d}"
        extra = {"method": run.config.method_name, "step": run.step, "checkpoint": str(run.checkpoint)}
    print(backend_line(model.config.raster, resolve_device(args.device)))
    metrics = evaluate(model, dm, save_dir=out if args.save_images else None)
    metrics.update({"scene": dm.scene_name, **extra})
    write_metrics_json(out / "metrics.json", metrics)
    dssim = f"D-SSIM {metrics['dssim']:.4f}  " if math.isfinite(metrics.get("dssim", float("nan"))) else ""
    lpips = f"LPIPS {metrics['lpips']:.4f}  " if metrics.get("lpips") is not None else ""
    print(f"PSNR {metrics['psnr']:.3f} dB  SSIM {metrics['ssim']:.4f}  {dssim}{lpips}"
          f"{metrics['num_gaussians']} Gaussians  -> {out / 'metrics.json'}")
    return metrics


def entrypoint() -> None:
    run_cli("eg-eval", main, parse_cli("eg-eval", EvalArgs, "Evaluate an ExploreGS run or a 3DGS PLY."))


if __name__ == "__main__":
    entrypoint()
