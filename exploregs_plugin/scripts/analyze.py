"""eg-analyze: the Blur-Trap diagnostics; each writes a PNG figure and the numbers (CSV + JSON).

    eg-analyze grad-branches --data builtin:default --max-steps 300 --every 25
    eg-analyze grad-directions --run RUN
    eg-analyze blending --run RUN --view 0 --pixel 70 50
    eg-analyze nearside --run RUN --checkpoints all
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
import torch
import tyro

from exploregs_plugin.analysis import plots
from exploregs_plugin.analysis.blending import (
    blending_by_rank, blending_by_visibility, composited_pairs, image_gradient, pixel_blending, screen_gradients,
)
from exploregs_plugin.analysis.branches import CURVES, branch_gradients
from exploregs_plugin.analysis.directions import REFERENCES, branch_cosines
from exploregs_plugin.analysis.nearside import DEPTH_TOLERANCE
from exploregs_plugin.analysis.nearside_report import (
    cancellation_rows, gaussian_rows, pixel_rows, plot_nearside, scene_views,
)
from exploregs_plugin.analysis.probing import TrainSpec, train_and_probe
from exploregs_plugin.analysis.sampling import pipeline_view, probe_steps, train_problems
from exploregs_plugin.analysis.tensorboard import pipeline_branch_norms
from exploregs_plugin.io.checkpoint import list_checkpoints, resolve_run
from exploregs_plugin.engine.pipeline import Pipeline
from exploregs_plugin.runs import load_run
from exploregs_plugin.scripts import parse_cli, run_cli
from exploregs_plugin.strategies import DefaultStrategy

Train = Annotated[TrainSpec, tyro.conf.arg(name="")]


@dataclass
class _RunOrTrain:
    run: Path | None = None
    """Analyse this run (grad-branches: each of its checkpoints; otherwise the latest) instead of
    training a new run into OUT/run."""
    train: Train = field(default_factory=TrainSpec)


@dataclass
class GradBranches(_RunOrTrain):
    """Per-view mean norm of the position gradient through each branch, over iterations."""

    every: int = 25
    """When training: probe every this many steps (and at 0 and the end)."""
    views: int = 4
    """Training views per probe (evenly spaced); the norms are averaged over them."""
    out: Path = Path("outputs/analysis/grad-branches")
    """Output folder: grad_branches.png / .csv / .json (and run/ when training)."""


@dataclass
class GradDirections(_RunOrTrain):
    """Histograms of |cos| between each branch's single-view gradient and the ray / optical axis."""

    views: int = 8
    """Training views, one backward pass each (evenly spaced)."""
    bins: int = 20
    """Histogram bins over [0, 1]."""
    out: Path = Path("outputs/analysis/grad-directions")
    """Output folder: grad_directions.png / .csv / .json (and run/ when training)."""


@dataclass
class Blending:
    """The Gaussians blended at one pixel (gradient, depth, T) and the same by depth rank over a view."""

    run: Path | None = None
    """A run folder (latest checkpoint) or a checkpoint file (required)."""
    view: int = 0
    """Index of the view within --split."""
    split: Literal["train", "test"] = "train"
    """Which views --view indexes."""
    pixel: tuple[int, int] | None = None
    """Pixel column X and row Y; unset: the pixel where the most Gaussians are blended."""
    max_rank: int = 40
    """Largest depth rank shown in the scene-wide profile."""
    out: Path = Path("outputs/analysis/blending")
    """Output folder: blending_pixel.*, blending_ranks.*, blending_visibility.* (png, csv, json)."""
    device: str = "auto"
    """Where to compute: auto (CUDA when available, else CPU), cpu, cuda or cuda:N."""


@dataclass
class Nearside:
    """The near-side trap: how many training views see the occluded region, and the transmittance
    and densification statistic of the Gaussians there (needs depth and region masks: built-in scenes)."""

    run: Path | None = None
    """A run folder or a checkpoint file (required)."""
    checkpoints: Literal["latest", "all", "none"] = "latest"
    """Gaussian statistics at the latest checkpoint only, at each checkpoint of the run, or not at all
    (pixels only: a few renders)."""
    tol: float = DEPTH_TOLERANCE
    """Relative depth agreement for 'seen' and 'on the surface' (the scene generator's 2%)."""
    cancellation_views: tuple[int, ...] = ()
    """Training views (indices) in which to compare each Gaussian's net screen-space gradient with the
    sum of its per-pixel parts, at the latest checkpoint (a scene-wide pass per view: seconds each)."""
    train_pixels: bool = True
    """Also split the training views' occluded pixels (the slower part: every view against every view)."""
    out: Path = Path("outputs/analysis/nearside")
    """Output folder: nearside_pixels.csv, nearside_references.csv, nearside_gaussians.csv,
    nearside_cancellation.csv, nearside.json, nearside.png."""
    device: str = "auto"
    """Where to compute: auto (CUDA when available, else CPU), cpu, cuda or cuda:N."""


def _run_label(pipeline: Pipeline, method: str, step: int) -> str:
    return f"{pipeline.datamanager.scene_name}, {method}, step {step}"


def _loaded_or_trained(run: Path | None, spec: TrainSpec, out: Path) -> tuple[Pipeline, int, str, Path]:
    """(pipeline, step, method, run folder) of --run, or of a run trained into OUT/run."""
    if run is not None:
        loaded = load_run(run, spec.device)
        return loaded.pipeline, loaded.step, loaded.config.method_name, loaded.run_dir
    trainer = train_and_probe(spec.trainer_config(out / "run"), [], lambda p, s: None)
    return trainer.pipeline, trainer.schedule.max_steps, spec.method, trainer.run_dir


def grad_branches(args: GradBranches) -> dict[str, Any]:
    rows: list[dict[str, Any]] = []

    def probe(pipeline: Pipeline, step: int) -> None:
        norms = pipeline_branch_norms(pipeline, step, args.views)
        rows.append({"step": step, "num_gaussians": pipeline.model.num_gaussians, **norms,
                     "ratio_mean2d_cov": norms["mean2d"] / norms["cov"] if norms["cov"] > 0 else None,
                     "ratio_mean2d_sh": norms["mean2d"] / norms["sh"] if norms["sh"] > 0 else None})

    if args.run is not None:
        run_dir, _ = resolve_run(args.run)
        checkpoints = list_checkpoints(run_dir)
        if not checkpoints:
            raise ValueError(f"{run_dir} has no checkpoints to analyse")
        for ckpt in checkpoints:
            loaded = load_run(ckpt, args.train.device)
            probe(loaded.pipeline, loaded.step)
            method, scene, run_folder = loaded.config.method_name, loaded.pipeline.datamanager.scene_name, run_dir
    else:
        trainer = train_and_probe(args.train.trainer_config(args.out / "run"),
                                  probe_steps(args.train.max_steps, args.every), probe)  # fmt: skip
        method, scene, run_folder = args.train.method, trainer.pipeline.datamanager.scene_name, trainer.run_dir
    plots.write_csv(args.out / "grad_branches.csv", rows)
    result = {"scene": scene, "method": method, "run": str(run_folder), "views_per_probe": args.views,
              "curves": list(CURVES), "rows": rows}  # fmt: skip
    plots.write_json(args.out / "grad_branches.json", result)
    plots.plot_branch_norms(rows, args.out / "grad_branches.png",
                            title=f"position gradient by branch ({scene}, {method})")
    last = rows[-1]
    print(f"step {last['step']}: |g| mean2d {last['mean2d']:.3g}, cov {last['cov']:.3g}, sh {last['sh']:.3g}, "
          f"total {last['total']:.3g} -> {args.out / 'grad_branches.png'}")
    return result


def grad_directions(args: GradDirections) -> dict[str, Any]:
    pipeline, step, method, run_dir = _loaded_or_trained(args.run, args.train, args.out)
    means = pipeline.params["means"].detach()
    pooled: dict[str, dict[str, list[np.ndarray]]] = {b: {r: [] for r in REFERENCES} for b in CURVES}
    for view in train_problems(pipeline, args.views, step):
        grads = branch_gradients(view)
        for branch, per_ref in branch_cosines(grads, means, view.camera).items():
            for ref, values in per_ref.items():
                pooled[branch][ref].append(values.double().cpu().numpy())
    cosines = {b: {r: np.concatenate(v) if v else np.zeros(0) for r, v in refs.items()} for b, refs in pooled.items()}
    edges = np.linspace(0.0, 1.0, args.bins + 1)
    rows, summary = [], {}
    for branch, refs in cosines.items():
        summary[branch] = {}
        for ref, values in refs.items():
            counts = np.histogram(values, bins=edges)[0]
            n = len(values)
            summary[branch][ref] = {
                "n": n,
                "median": float(np.median(values)) if n else None,
                "mean": float(values.mean()) if n else None,
                "max": float(values.max()) if n else None,
                "frac_below_0.01": float((values < 0.01).mean()) if n else None,
                "frac_above_0.5": float((values > 0.5).mean()) if n else None,
            }
            rows += [{"branch": branch, "reference": ref, "bin_lo": float(edges[i]), "bin_hi": float(edges[i + 1]),
                      "count": int(counts[i]), "fraction": float(counts[i] / max(n, 1))}
                     for i in range(args.bins)]  # fmt: skip
    plots.write_csv(args.out / "grad_directions.csv", rows)
    result = {"scene": pipeline.datamanager.scene_name, "method": method, "run": str(run_dir), "step": step,
              "views": args.views, "summary": summary}  # fmt: skip
    plots.write_json(args.out / "grad_directions.json", result)
    plots.plot_direction_histograms(cosines, args.out / "grad_directions.png",
                                    bins=args.bins, title=f"single-view gradients, {_run_label(pipeline, method, step)}")
    for branch in CURVES:
        s = summary[branch]["ray"]
        if s["n"]:
            print(f"{branch:7s} |cos| with ray: median {s['median']:.3g}, max {s['max']:.3g} (n={s['n']})")
    return result


def _densify_threshold(pipeline: Pipeline) -> float:
    """The run's grow_grad2d (NDC units); strategies without one get the 3DGS default."""
    value = getattr(pipeline.strategy, "grow_grad2d", None)
    return float(value) if value is not None else DefaultStrategy().grow_grad2d


def blending(args: Blending) -> dict[str, Any]:
    if args.run is None:
        raise ValueError("blending needs a run: eg-analyze blending --run RUN_DIR")
    loaded = load_run(args.run, args.device)
    pipeline, step = loaded.pipeline, loaded.step
    dm = pipeline.datamanager
    count = len(dm.train_cameras if args.split == "train" else dm.test_cameras)
    if not 0 <= args.view < count:
        raise ValueError(f"--view {args.view} is out of range: the {args.split} split has {count} views")
    camera, target, _ = (dm.train_item if args.split == "train" else dm.test_item)(args.view)
    view = pipeline_view(pipeline, camera, target, step)
    threshold = _densify_threshold(pipeline)

    pairs = composited_pairs(pipeline.params, camera, view.settings, sh_degree=view.sh_degree,
                             background=view.background, image_grad=image_gradient(view))  # fmt: skip
    if args.pixel is None:
        if pairs["pixel"].numel() == 0:
            raise ValueError(f"no Gaussian is blended anywhere in {args.split} view {args.view}")
        per_pixel = torch.bincount(pairs["pixel"], minlength=camera.width * camera.height)
        flat = int(torch.argmax(per_pixel))
        x, y = flat % camera.width, flat // camera.width
    else:
        x, y = args.pixel
        if not (0 <= x < camera.width and 0 <= y < camera.height):
            raise ValueError(f"--pixel {x} {y} is outside the {camera.width}x{camera.height} image")

    trace = pixel_blending(view, x, y)
    pixel_rows = [{"order": i, "id": int(trace["ids"][i]), "depth": float(trace["depths"][i]),
                   "alpha": float(trace["alphas"][i]), "T_before": float(trace["T_before"][i]),
                   "grad_image": float(trace["grad_image"][i]), "grad_pixel": float(trace["grad_pixel"][i]),
                   "above_threshold": bool(trace["grad_image"][i] > threshold)}
                  for i in range(len(trace["ids"]))]  # fmt: skip
    if not pixel_rows:
        raise ValueError(f"no Gaussian is blended at pixel ({x}, {y}) of {args.split} view {args.view}")
    label = f"{_run_label(pipeline, loaded.config.method_name, step)}, {args.split} view {args.view}"
    plots.write_csv(args.out / "blending_pixel.csv", pixel_rows)
    plots.write_json(args.out / "blending_pixel.json", {
        "run": str(loaded.run_dir), "step": step, "split": args.split, "view": args.view, "pixel": [x, y],
        "threshold_ndc": threshold, "T_final": float(trace["T_final"]), "rows": pixel_rows})  # fmt: skip
    plots.plot_pixel_blending(pixel_rows, threshold, args.out / "blending_pixel.png",
                              title=f"pixel ({x}, {y}), {label}")

    grad_ndc = screen_gradients(view)["image"]
    profile = blending_by_rank(pairs, grad_ndc, threshold, max_rank=args.max_rank,
                               image_size=(camera.width, camera.height))  # fmt: skip
    rank_rows = [{"rank": int(profile["rank"][k]), "pixels": int(profile["pixels"][k]),
                  "mean_grad": float(profile["mean_grad"][k]), "mean_pixel_grad": float(profile["mean_pixel_grad"][k]),
                  "mean_T": float(profile["mean_T"][k]), "frac_above": float(profile["frac_above"][k])}
                 for k in range(len(profile["rank"]))]  # fmt: skip
    plots.write_csv(args.out / "blending_ranks.csv", rank_rows)
    plots.write_json(args.out / "blending_ranks.json", {
        "run": str(loaded.run_dir), "step": step, "split": args.split, "view": args.view,
        "threshold_ndc": threshold, "pairs": int(pairs["rank"].numel()), "rows": rank_rows})  # fmt: skip
    plots.plot_rank_profile(rank_rows, threshold, args.out / "blending_ranks.png", title=f"all pixels, {label}")

    vis = blending_by_visibility(pairs, grad_ndc, threshold)
    vis_rows = [{"lo": float(vis["lo"][b]), "hi": float(vis["hi"][b]), "gaussians": int(vis["gaussians"][b]),
                 "mean_grad": float(vis["mean_grad"][b]), "frac_above": float(vis["frac_above"][b])}
                for b in range(len(vis["lo"]))]  # fmt: skip
    plots.write_csv(args.out / "blending_visibility.csv", vis_rows)
    plots.write_json(args.out / "blending_visibility.json", {
        "run": str(loaded.run_dir), "step": step, "split": args.split, "view": args.view,
        "threshold_ndc": threshold, "rows": vis_rows})  # fmt: skip
    plots.plot_visibility(vis_rows, threshold, args.out / "blending_visibility.png", title=f"Gaussians, {label}")
    print(f"pixel ({x}, {y}): {len(pixel_rows)} Gaussians blended, "
          f"{sum(r['above_threshold'] for r in pixel_rows)} above grow_grad2d = {threshold:g} -> {args.out}")
    return {"pixel": pixel_rows, "ranks": rank_rows, "visibility": vis_rows, "xy": (x, y), "threshold": threshold}


def nearside(args: Nearside) -> dict[str, Any]:
    if args.run is None:
        raise ValueError("nearside needs a run: eg-analyze nearside --run RUN_DIR")
    if not 0.0 < args.tol < 1.0:
        raise ValueError(f"--tol must be in (0, 1), got {args.tol}")
    loaded = load_run(args.run, args.device)
    pipeline = loaded.pipeline
    train, test = scene_views(pipeline.datamanager, "train"), scene_views(pipeline.datamanager, "test")
    bad = [v for v in args.cancellation_views if not 0 <= v < len(train.cameras)]
    if bad:
        raise ValueError(f"--cancellation-views {bad} out of range: the train split has {len(train.cameras)} views")
    pixels, references = [], []
    for split, views in (("test", test), ("train", train))[: 2 if args.train_pixels else 1]:
        rows, refs = pixel_rows(pipeline, split, views, train, args.tol)
        pixels, references = pixels + rows, references + refs
    if not any(r["split"] == "test" for r in references):
        raise ValueError("the test views have no occluded pixels: there is nothing to measure")
    targets = {"all": list_checkpoints(loaded.run_dir), "latest": [loaded.checkpoint], "none": []}[args.checkpoints]
    gaussians: list[dict[str, Any]] = []
    for ckpt in targets:
        at = loaded if ckpt == loaded.checkpoint else load_run(ckpt, args.device)
        gaussians += gaussian_rows(at.pipeline, at.step, train, _densify_threshold(at.pipeline), args.tol)
    plots.write_csv(args.out / "nearside_pixels.csv", pixels)
    if gaussians:
        plots.write_csv(args.out / "nearside_gaussians.csv", gaussians)
    plots.write_csv(args.out / "nearside_references.csv", references)
    cancellation = cancellation_rows(pipeline, loaded.step, train, list(args.cancellation_views), args.tol)
    if cancellation:
        plots.write_csv(args.out / "nearside_cancellation.csv", cancellation)
    result = {"run": str(loaded.run_dir), "step": loaded.step, "method": loaded.config.method_name,
              "tol": args.tol, "threshold_ndc": _densify_threshold(pipeline), "pixels": pixels,
              "references": references, "gaussians": gaussians, "cancellation": cancellation}  # fmt: skip
    plots.write_json(args.out / "nearside.json", result)
    plot_nearside(pixels, gaussians, args.out / "nearside.png",
                  title=_run_label(pipeline, loaded.config.method_name, loaded.step))
    unseen = next(r for r in pixels if r["split"] == "test" and r["view"] == "all" and r["part"] == "occluded")
    print(f"occluded test pixels seen by no training view: {unseen['share_pixels']:.1%} of the pixels, "
          f"{unseen['share_sq_error']:.1%} of the squared error -> {args.out}")
    return result


COMMANDS = {
    "grad-branches": (GradBranches, grad_branches),
    "grad-directions": (GradDirections, grad_directions),
    "blending": (Blending, blending),
    "nearside": (Nearside, nearside),
}


def main(args: GradBranches | GradDirections | Blending | Nearside) -> dict[str, Any]:
    for cls, fn in COMMANDS.values():
        if isinstance(args, cls):
            return fn(args)
    raise ValueError(f"unknown analysis arguments {type(args).__name__}")


def parse(argv: list[str] | None = None) -> GradBranches | GradDirections | Blending | Nearside:
    descriptions = {name: (cls.__doc__ or "").strip() for name, (cls, _) in COMMANDS.items()}
    union = tyro.extras.subcommand_type_from_defaults({name: cls() for name, (cls, _) in COMMANDS.items()},
                                                      descriptions)  # fmt: skip
    return parse_cli("eg-analyze", union, "Blur-Trap diagnostics: gradient branches, their directions, "
                     "alpha-blending attenuation, the near-side trap (figures + CSV/JSON).", argv)


def entrypoint() -> None:
    run_cli("eg-analyze", main, parse())


if __name__ == "__main__":
    entrypoint()
