"""eg-export: write a trained run's Gaussians as a scene file: a standard 3DGS PLY (default), a
PlayCanvas compressed PLY, an antimatter15 .splat or a Niantic .spz; or as a folder with a static
web page that shows them (``--format web``).

By default the file is in the dataset's original coordinates (the training normalisation is
undone), so it lines up with the dataset's own cameras and points in other tools.
``--max-gaussians N`` keeps the N Gaussians that paint most of the training views (optionally
fine-tuned, ``--finetune-steps``): a smaller splat to share.
"""

from __future__ import annotations

import shlex
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, Mapping

import torch
import tyro
from torch import Tensor

from exploregs_plugin.io.ply import normalization_terms
from exploregs_plugin.io.scene_files import (
    SUFFIXES,
    SceneExport,
    format_for,
    write_scene,
)
from exploregs_plugin.runs import load_run
from exploregs_plugin.runs.load import LoadedRun
from exploregs_plugin.runs.scene import dataset_normalization
from exploregs_plugin.runs.simplify import simplify
from exploregs_plugin.scripts import parse_cli, run_cli
from exploregs_plugin.viewer.web_page import WebPage, write_web_page

WEB = "web"


@dataclass
class ExportArgs:
    path: tyro.conf.Positional[Path]
    """A run folder (uses its latest checkpoint) or a checkpoint file."""
    out: Path | None = None
    """Output file (default: RUN/exports/scene-step-XXXXXXX.EXT, EXT the format's suffix)."""
    format: Literal["ply", "splat", "spz", "compressed-ply", "web"] | None = None
    """File format: ply (standard 3DGS, lossless), compressed-ply (PlayCanvas, .compressed.ply),
    splat (antimatter15, no SH beyond the colour) or spz (Niantic); web: --out is a folder with a
    static page showing the scene from the first training camera (serve it with any web server).
    Unset: from --out's suffix (.ply, .compressed.ply, .splat, .spz), else ply."""
    spz_sh_bits: tuple[int, int] = (8, 8)
    """.spz: bits kept of each SH coefficient of band 1 and of bands 2-3, 1-8. 8 8 keeps all that the
    file's bytes hold (beer: the PLY's test PSNR at 33 bytes a Gaussian); 5 4, the reference
    writer's, compresses to about half that and loses most small view-dependent colour (beer: -0.55 dB)."""
    max_gaussians: int | None = None
    """Keep only this many Gaussians: those with the largest compositing weight (alpha x
    transmittance) summed over the training views' pixels times their largest weight at one pixel
    (so small Gaussians that paint texture alone are kept). Unset: all."""
    finetune_steps: int = 0
    """With --max-gaussians: train the kept Gaussians this many steps more (the run's final
    learning rates, no densification) so they take up what the removed ones painted."""
    frame: Literal["original", "normalized"] = "original"
    """Coordinates to write: the dataset's original frame, or the normalised training frame."""
    ascii: bool = False
    """Write an ASCII PLY instead of binary little-endian (larger; for inspection; ply only)."""
    device: str = "auto"
    """Where to compute: auto (CUDA when available, else CPU), cpu, cuda or cuda:N."""
    time: float | None = None
    """Dynamic runs: write the Gaussians deformed to this time in [0, 1] (unset: the canonical ones)."""


def gaussians_at(run: LoadedRun, time: float | None) -> Mapping[str, Tensor]:
    """The run's raw parameters: the canonical ones, or a dynamic run's deformed to ``time``."""
    model = run.pipeline.model
    if time is None:
        return model.params
    if not model.parts:
        raise ValueError(f"--time is for runs of a dynamic (4D) method; {run.run_dir} is static")
    if not 0.0 <= time <= 1.0:
        raise ValueError(f"--time must be in [0, 1], got {time}")
    with torch.no_grad():
        return {k: v.detach() for k, v in model.params_at(time).items()}


def output_path(args: ExportArgs, run: LoadedRun) -> tuple[Path, str]:
    """(file to write, its format): --out / --format, or RUN/exports/scene-step-N[-time-T].EXT."""
    if args.out is not None:
        if args.format == WEB:
            return args.out, WEB
        return args.out, format_for(args.out, args.format, default="ply")
    fmt = args.format or "ply"
    moment = "" if args.time is None else f"-time-{args.time:g}"
    kept = "" if args.max_gaussians is None else f"-keep-{args.max_gaussians}"
    if fmt == WEB:
        return run.run_dir / "exports" / f"web-step-{run.step:07d}{moment}{kept}", fmt
    return run.run_dir / "exports" / f"scene-step-{run.step:07d}{moment}{kept}{SUFFIXES[fmt]}", fmt


def header_comments(args: ExportArgs, run: LoadedRun, normalization: Any) -> list[str]:
    """What the PLY formats record in their header: step, frame, time and normalisation."""
    translation, scale = normalization_terms(normalization)
    return [f"step {run.step}, frame {args.frame}" + ("" if args.time is None else f", time {args.time:g}"),
            f"normalization x_norm = (x_orig + t) * s, t = {translation.tolist()}, s = {scale!r}"]


def report(result: SceneExport, frame: str, model_sh_degree: int) -> None:
    size = result.size_bytes
    print(f"wrote {result.written} Gaussians as {result.format} (SH degree {result.sh_degree}, {frame} frame, "
          f"{size} bytes, {size / max(result.written, 1):.1f} per Gaussian) -> {result.path}")
    if result.sh_degree < model_sh_degree:
        print(f"{result.format} holds no SH bands above {result.sh_degree}; the run's degree-{model_sh_degree} "
              f"view-dependent colour is left out")
    if result.dropped:
        print(f"left out {result.dropped} Gaussians with non-finite values")


def reduce(args: ExportArgs, run: LoadedRun) -> None:
    """--max-gaussians / --finetune-steps: prune (and fine-tune) the loaded run in place."""
    if args.max_gaussians is None:
        if args.finetune_steps:
            raise ValueError("--finetune-steps fine-tunes what --max-gaussians keeps; give --max-gaussians too")
        return
    done = simplify(run.pipeline, run.step, args.max_gaussians, args.finetune_steps)
    tuned = f", then fine-tuned {done.finetune_steps} steps" if done.finetune_steps else ""
    print(f"kept {done.after} of {done.before} Gaussians ({100 * done.kept_weight_share:.1f}% of the training "
          f"views' compositing weight){tuned}")


def web_page(args: ExportArgs, run: LoadedRun, params: Mapping[str, Tensor], out: Path) -> WebPage:
    """--format web: the page shows the training frame, opening at the first training camera."""
    if args.frame != "original" or args.ascii:
        raise ValueError("--frame and --ascii are for scene files; a web page shows the training frame")
    dm, model = run.pipeline.datamanager, run.pipeline.model
    page = write_web_page(out, params, model.config.sh_degree, dm.train_cameras, title=f"{dm.scene_name} (ExploreGS)",
                          background=dm.background)
    print(f"wrote a web page of {page.num_gaussians} Gaussians ({page.size_bytes} bytes) -> {page.directory}")
    print(f"serve it with: cd {shlex.quote(str(page.directory))} && python3 -m http.server 8000 --bind 127.0.0.1   "
          f"(then open http://127.0.0.1:8000/)")
    if page.dropped:
        print(f"left out {page.dropped} Gaussians with non-finite values")
    return page


def main(args: ExportArgs) -> SceneExport | WebPage:
    run = load_run(args.path, args.device)
    out, fmt = output_path(args, run)
    reduce(args, run)
    params = gaussians_at(run, args.time)
    if fmt == WEB:
        return web_page(args, run, params, out)
    normalization = dataset_normalization(run.pipeline.datamanager) if args.frame == "original" else None
    model = run.pipeline.model
    # the antialiased (2D-filter) rasterizer: .spz's header flag, the PLYs' SplatRenderMode comment
    result = write_scene(out, params, normalization, fmt=fmt, comments=header_comments(args, run, normalization),
                         antialiased=model.config.raster.antialiased, text=args.ascii,
                         spz_sh_bits=args.spz_sh_bits)
    report(result, args.frame, model.config.sh_degree)
    return result


def entrypoint() -> None:
    description = "Export a trained ExploreGS run as a 3DGS PLY, compressed PLY, .splat, .spz or a web page."
    run_cli("eg-export", main, parse_cli("eg-export", ExportArgs, description))


if __name__ == "__main__":
    entrypoint()
