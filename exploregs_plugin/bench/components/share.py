"""What sharing a splat costs: each export format's size and what its quantisation does to the
test views, and the smaller splats of ``eg-export --max-gaussians`` (with and without fine-tuning).

    python -m exploregs_plugin.bench.components.share RUN [--fractions 1 2 4 8] [--finetune-steps 300] [--out FILE.md]

Formats: every test view is rendered from the file read back (mapped into the run's frame as
eg-render does) and scored against the ground truth and against the render of the run's own
float32 parameters (PSNR to the float render: how far the format moves the image). Smaller
splats: the run is loaded afresh for each count, pruned to N / fraction Gaussians by their
compositing weight over the training views, optionally fine-tuned, and scored on the test views.
For .spz at the reference's SH bits, which quantised value costs the PSNR (each alone).
Prints markdown tables (written to ``--out`` too).
"""

from __future__ import annotations

import argparse
import math
import tempfile
import time
from pathlib import Path
from typing import Any, Mapping

import torch
from torch import Tensor

from exploregs_plugin.evaluation.metrics import evaluate
from exploregs_plugin.io.scene_files import SCENE_FORMATS, SUFFIXES, read_scene, write_scene
from exploregs_plugin.runs import dataset_normalization, load_run
from exploregs_plugin.runs.scene import model_from_params
from exploregs_plugin.runs.simplify import simplify

def _psnr_to(reference: Tensor, image: Tensor) -> float:
    mse = float(((reference.double() - image.double()) ** 2).mean())
    return math.inf if mse <= 0.0 else -10.0 * math.log10(mse)


def _renders(params: Mapping[str, Tensor], sh_degree: int, run: Any) -> list[Tensor]:
    model = model_from_params(dict(params), sh_degree, run.pipeline.model.config.raster, "cpu")
    dm = run.pipeline.datamanager
    with torch.no_grad():
        return [model.render(camera, sh_degree, dm.background)[0].clamp(0, 1) for camera in dm.test_cameras]


def format_rows(run: Any, folder: Path) -> list[dict[str, Any]]:
    """One row per format: bytes, bytes per Gaussian, test PSNR, PSNR to the float render."""
    model, dm = run.pipeline.model, run.pipeline.datamanager
    params = {k: v.detach().cpu() for k, v in model.params.items()}
    normalization = dataset_normalization(dm)
    sh_degree = model.config.sh_degree
    reference = _renders(params, sh_degree, run)
    rows = []
    variants = [(fmt, {}) for fmt in SCENE_FORMATS] + [("spz", {"spz_sh_bits": (8, 8)})]
    for fmt, options in variants:
        name = fmt + "".join(f" sh bits {' '.join(map(str, v))}" for v in options.values())
        path = folder / f"scene-{len(options)}{SUFFIXES[fmt]}"
        start = time.perf_counter()
        written = write_scene(path, params, normalization, fmt=fmt, **options)
        seconds = time.perf_counter() - start
        scene = read_scene(path, normalization)
        images = _renders(scene.params, scene.sh_degree, run)
        to_float = min(_psnr_to(r, i) for r, i in zip(reference, images))
        scored = evaluate(model_from_params(scene.params, scene.sh_degree, model.config.raster, "cpu"), dm)
        size = path.stat().st_size
        rows.append({"format": name, "gaussians": written.written, "sh_degree": scene.sh_degree, "bytes": size,
                     "bytes_per_gaussian": size / max(written.written, 1), "test_psnr": scored["psnr"],
                     "lpips": scored["lpips"],
                     "worst_view_psnr_to_float": to_float, "write_seconds": seconds})
    return rows


def attribution_rows(run: Any, folder: Path, fmt: str = "spz", **options: Any) -> list[dict[str, Any]]:
    """Which quantised value costs the PSNR: the float32 parameters with one of them replaced by the
    file's (a format that keeps the row order: .spz, .ply), test PSNR of each."""
    model, dm = run.pipeline.model, run.pipeline.datamanager
    params = {k: v.detach().cpu() for k, v in model.params.items()}
    normalization = dataset_normalization(dm)
    path = folder / f"attribution{SUFFIXES[fmt]}"
    write_scene(path, params, normalization, fmt=fmt, **options)
    stored = read_scene(path, normalization).params
    if stored["means"].shape != params["means"].shape:
        raise ValueError(f"{fmt}: the file holds another number of rows; attribution needs every row kept in order")
    rows = []
    for name in ("means", "scales", "quats", "opacities", "sh0", "shN"):
        mixed = {**params, name: stored[name]}
        scored = evaluate(model_from_params(mixed, model.config.sh_degree, model.config.raster, "cpu"), dm)
        rows.append({"quantised": name, "test_psnr": scored["psnr"]})
    return rows


def count_rows(path: Path, fractions: list[int], finetune_steps: int, folder: Path) -> list[dict[str, Any]]:
    """One row per (fraction, fine-tuning): Gaussians, share of the weight kept, test PSNR, PLY and SPZ bytes."""
    rows = []
    for fraction in fractions:
        for steps in sorted({0, finetune_steps}) if fraction > 1 else [0]:
            run = load_run(path, "cpu")
            n = run.pipeline.model.num_gaussians
            start = time.perf_counter()
            done = simplify(run.pipeline, run.step, max(n // fraction, 1), steps)
            seconds = time.perf_counter() - start
            model, dm = run.pipeline.model, run.pipeline.datamanager
            scored = evaluate(model, dm)
            sizes = {}
            for fmt in ("ply", "spz"):
                file = folder / f"x{fraction}-{steps}{SUFFIXES[fmt]}"
                write_scene(file, model.params, dataset_normalization(dm), fmt=fmt)
                sizes[fmt] = file.stat().st_size
            rows.append({"fraction": fraction, "finetune_steps": steps, "gaussians": done.after,
                         "weight_kept": done.kept_weight_share, "test_psnr": scored["psnr"], "lpips": scored["lpips"],
                         "ssim": scored["ssim"], "ply_bytes": sizes["ply"], "spz_bytes": sizes["spz"],
                         "seconds": seconds})
    return rows


def _mb(n: int) -> str:
    return f"{n / 1e6:.2f}"


def _lpips(value: float | None) -> str:
    """LPIPS to 4 decimals, n/a where its weights are not installed."""
    return "n/a" if value is None else f"{value:.4f}"


def tables(formats: list[dict[str, Any]], counts: list[dict[str, Any]],
           attribution: list[dict[str, Any]] = ()) -> str:
    lines = ["| format | Gaussians | SH | MB | bytes/Gaussian | test PSNR | LPIPS | worst view, PSNR to float render |",
             "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for r in formats:
        lines.append(f"| {r['format']} | {r['gaussians']} | {r['sh_degree']} | {_mb(r['bytes'])} | "
                     f"{r['bytes_per_gaussian']:.1f} | {r['test_psnr']:.2f} | {_lpips(r['lpips'])} | "
                     f"{r['worst_view_psnr_to_float']:.1f} |")
    if attribution:
        lines += ["", "| spz (SH bits 5 4): only this value quantised | test PSNR |", "|---|---:|"]
        lines += [f"| {r['quantised']} | {r['test_psnr']:.2f} |" for r in attribution]
    lines += ["", "| kept | fine-tune steps | Gaussians | weight kept | test PSNR | SSIM | LPIPS | PLY MB | SPZ MB | "
                  "seconds |", "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in counts:
        lines.append(f"| x1/{r['fraction']} | {r['finetune_steps']} | {r['gaussians']} | {r['weight_kept']:.3f} | "
                     f"{r['test_psnr']:.2f} | {r['ssim']:.4f} | {_lpips(r['lpips'])} | {_mb(r['ply_bytes'])} | "
                     f"{_mb(r['spz_bytes'])} | {r['seconds']:.1f} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run", type=Path, help="a run folder or checkpoint")
    ap.add_argument("--fractions", type=int, nargs="+", default=[1, 2, 4, 8])
    ap.add_argument("--finetune-steps", type=int, default=300)
    ap.add_argument("--out", type=Path, default=None, help="also write the tables to this markdown file")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        run = load_run(args.run, "cpu")
        formats = format_rows(run, Path(tmp))
        attribution = attribution_rows(run, Path(tmp))
        counts = count_rows(args.run, args.fractions, args.finetune_steps, Path(tmp))
    text = tables(formats, counts, attribution)
    print(text)
    if args.out is not None:
        args.out.write_text(text + "\n")


if __name__ == "__main__":
    main()
