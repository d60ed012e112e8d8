"""eg-export: write a trained run's Gaussians as a standard 3DGS PLY.

By default the PLY is in the dataset's original coordinates (the training normalisation is
undone), so it lines up with the dataset's own cameras and points in other tools.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import torch
import tyro

from exploregs_plugin.io.ply import PlyExport, export_ply, normalization_terms
from exploregs_plugin.runs.scene import dataset_normalization
from exploregs_plugin.runs import load_run
from exploregs_plugin.scripts import parse_cli, run_cli


@dataclass
class ExportArgs:
    path: tyro.conf.Positional[Path]
    """A run folder (uses its latest checkpoint) or a checkpoint file."""
    out: Path | None = None
    """Output PLY file (default: RUN/exports/scene-step-XXXXXXX.ply)."""
    frame: Literal["original", "normalized"] = "original"
    """Coordinates to write: the dataset's original frame, or the normalised training frame."""
    ascii: bool = False
    """Write an ASCII PLY instead of binary little-endian (larger; for inspection)."""
    device: str = "auto"
    """Where to compute: auto (CUDA when available, else CPU), cpu, cuda or cuda:N."""
    time: float | None = None
    """Dynamic runs: write the Gaussians deformed to this time in [0, 1] (unset: the canonical ones)."""


def main(args: ExportArgs) -> PlyExport:
    run = load_run(args.path, args.device)
    model = run.pipeline.model
    params = model.params
    if args.time is not None:
        if not model.parts:
            raise ValueError(f"--time is for runs of a dynamic (4D) method; {run.run_dir} is static")
        if not 0.0 <= args.time <= 1.0:
            raise ValueError(f"--time must be in [0, 1], got {args.time}")
        with torch.no_grad():
            params = {k: v.detach() for k, v in model.params_at(args.time).items()}
    moment = "" if args.time is None else f"-time-{args.time:g}"
    out = args.out or run.run_dir / "exports" / f"scene-step-{run.step:07d}{moment}.ply"
    normalization = dataset_normalization(run.pipeline.datamanager) if args.frame == "original" else None
    translation, scale = normalization_terms(normalization)
    comments = [f"step {run.step}, frame {args.frame}" + ("" if args.time is None else f", time {args.time:g}"),
                f"normalization x_norm = (x_orig + t) * s, t = {translation.tolist()}, s = {scale!r}"]
    result = export_ply(out, params, normalization, text=args.ascii, comments=comments)
    print(f"wrote {result.written} Gaussians (SH degree {result.sh_degree}, {args.frame} frame) -> {result.path}")
    if result.dropped:
        print(f"left out {result.dropped} Gaussians with non-finite values")
    return result


def entrypoint() -> None:
    run_cli("eg-export", main, parse_cli("eg-export", ExportArgs, "Export a trained ExploreGS run as a standard 3DGS PLY."))


if __name__ == "__main__":
    entrypoint()
