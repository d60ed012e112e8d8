"""Far-region PSNR for captured scenes, which have no region masks of their own.

The built-in scenes know their far region from their generator. A captured scene (COLMAP,
transforms.json) does not, so here "far" is taken from one reference run of the scene: render each
test view's expected depth and alpha with the reference's final model; a pixel is covered when
alpha >= 0.5 and depth > 0, and far when it is covered and its depth is at least the ``quantile``
(default 0.75: the farthest quarter) of the depth over that view's covered pixels. Every method of
the scene is then scored on these same pixels, with the PSNR pooled over all test views as
``evaluation/metrics.py`` pools its regions.

Results are cached: ``RUN/far_region.json`` beside each scored run, and the masks of a scene in
the bench's results folder (``OUT/far_masks/<scene>.pt``), each with the fingerprint of the
reference (run folder, final checkpoint, step) and the quantile; a changed reference or quantile
recomputes them.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterator

import torch
from torch import Tensor

from exploregs_plugin.bench.runner import read_json
from exploregs_plugin.bench.spec import BenchSpec
from exploregs_plugin.io.config_files import load_config
from exploregs_plugin.evaluation.metrics import write_metrics_json
from exploregs_plugin.io.checkpoint import CheckpointError, atomic_torch_save, checkpoint_path
from exploregs_plugin.model.losses import pooled_psnr, psnr
from exploregs_plugin.runs.load import LoadedRun, load_run
from exploregs_plugin.engine.trainer import CONFIG_NAME, TrainerConfig

FAR_QUANTILE = 0.75
"""Default depth quantile: far = the farthest quarter of each view's covered pixels."""
COVERED_ALPHA = 0.5
"""A pixel is covered by the reference model when its accumulated alpha is at least this."""
RESULT_NAME = "far_region.json"
"""Per run folder: the run's far-region PSNR and what it was computed against."""
MASKS_DIR = "far_masks"
"""Under the bench's results folder: ``<scene>.pt``, the masks of that scene's reference."""


class FarRegionError(RuntimeError):
    """A run folder cannot be scored (no final checkpoint, other test views ...); one line."""


def describe_rule(quantile: float = FAR_QUANTILE) -> str:
    """The far set in words, for tables and JSON ("the farthest quarter" for 0.75)."""
    share = 1.0 - quantile
    part = "quarter" if abs(share - 0.25) < 1e-9 else f"{100.0 * share:g}%"
    return (f"the farthest {part} of each test view's covered pixels (alpha >= {COVERED_ALPHA:g}, depth > 0) "
            f"by the reference run's rendered depth: depth >= the {quantile:g} quantile over the covered pixels")


def check_quantile(quantile: float) -> float:
    """``quantile`` as a float in [0, 1] (0: every covered pixel is far, 1: only the farthest), or
    one line saying what came instead."""
    if isinstance(quantile, bool) or not isinstance(quantile, (int, float)) or not 0.0 <= quantile <= 1.0:
        raise ValueError(f"far-region quantile must be a number in [0, 1], got {quantile!r}")
    return float(quantile)


# ----------------------------------------------------------------------------- the rule (pure)
def covered_pixels(alpha: Tensor, depth: Tensor, min_alpha: float = COVERED_ALPHA) -> Tensor:
    """[H, W] bool: pixels the model draws something at, ``alpha >= min_alpha and depth > 0``.

    Expected depth is sum(w z) / alpha, so where alpha is small it is the depth of a faint haze
    (and 0 where alpha < 1e-10): such pixels say nothing about how far the scene is."""
    alpha, depth = _plane(alpha, "alpha"), _plane(depth, "depth")
    if alpha.shape != depth.shape:
        raise ValueError(f"alpha {tuple(alpha.shape)} and depth {tuple(depth.shape)} differ in shape")
    return (alpha >= min_alpha) & (depth > 0) & torch.isfinite(depth)


def depth_quantile(values: Tensor, quantile: float) -> Tensor:
    """The ``quantile`` of a 1-D float32 tensor, linear between order statistics as torch.quantile:
    v_(lo) + (v_(hi) - v_(lo)) (p - lo) at position p = quantile (n - 1), p in float32 as torch
    takes it, so both give the same threshold bit for bit. Sorting instead of torch.quantile,
    which refuses more than 2^24 values (a 16-megapixel view)."""
    values = values.reshape(-1).float()
    if values.numel() == 0:
        raise ValueError("depth_quantile: no values (a view without covered pixels)")
    ordered = values.sort().values
    q = torch.tensor(check_quantile(quantile), dtype=ordered.dtype, device=ordered.device)
    position = q * (ordered.numel() - 1)
    lo = min(int(position), ordered.numel() - 1)
    hi = min(lo + 1, ordered.numel() - 1)
    return torch.lerp(ordered[lo], ordered[hi], position - lo)


def far_mask(alpha: Tensor, depth: Tensor, quantile: float = FAR_QUANTILE,
             min_alpha: float = COVERED_ALPHA) -> Tensor:
    """[H, W] bool: covered pixels with depth >= the ``quantile`` of depth over the covered pixels
    (all False when nothing is covered). Per view, so that a view looking at near things only
    still has its own far part, and every view weighs in."""
    depth = _plane(depth, "depth").float()
    covered = covered_pixels(alpha, depth, min_alpha)
    if not bool(covered.any()):
        return covered
    return covered & (depth >= depth_quantile(depth[covered], quantile))


def masked_squared_error(image: Tensor, target: Tensor, mask: Tensor) -> tuple[float, int]:
    """(sum over masked pixels of the per-pixel mean squared error over RGB, pixel count), in
    float64 as evaluation.py sums its regions, so views can be pooled exactly."""
    if mask.shape != image.shape[:2] or image.shape != target.shape:
        raise ValueError(f"image {tuple(image.shape)}, target {tuple(target.shape)} and mask "
                         f"{tuple(mask.shape)} do not match")
    sq = ((image.double() - target.double()) ** 2).mean(dim=-1)
    mask = mask.to(sq.device)
    return float(sq[mask].sum()), int(mask.sum())


def _plane(value: Tensor, name: str) -> Tensor:
    """[H, W] from [H, W] or [H, W, 1]."""
    if value.dim() == 3 and value.shape[-1] == 1:
        value = value[..., 0]
    if value.dim() != 2:
        raise ValueError(f"{name} must be [H, W] or [H, W, 1], got {tuple(value.shape)}")
    return value


# ----------------------------------------------------------------------------- run folders
def final_checkpoint(run_dir: Path) -> Path:
    """The checkpoint the trainer writes when a run ends, ``checkpoints/step-<max_steps>.pt``:
    the numbers belong to the finished model, not to an interrupted run's newest checkpoint."""
    run_dir = Path(run_dir)
    try:
        config = load_config(run_dir / CONFIG_NAME)
    except (OSError, ValueError) as err:
        raise FarRegionError(f"{run_dir}: not a finished run folder ({err})") from err
    if not isinstance(config, TrainerConfig):
        raise FarRegionError(f"{run_dir}: {CONFIG_NAME} holds a {type(config).__name__}, not a TrainerConfig")
    path = checkpoint_path(run_dir, config.max_steps)
    if not path.is_file():
        raise FarRegionError(f"{run_dir}: no final checkpoint ({path.relative_to(run_dir)}): the run has not "
                             f"finished its {config.max_steps} steps, so there is no final model to render")
    return path


def run_fingerprint(run_dir: Path) -> dict[str, Any]:
    """What identifies a run's final model without loading it: the folder, the final checkpoint's
    name and step, and its size and modification time (a run trained again in the same folder
    writes the same name)."""
    path = final_checkpoint(run_dir)
    stat = path.stat()
    return {"run_dir": str(Path(run_dir).resolve()), "checkpoint": path.name,
            "step": int(path.stem.split("-")[-1]), "bytes": stat.st_size, "mtime_ns": stat.st_mtime_ns}


def _load_final(run_dir: Path, device: str) -> LoadedRun:
    try:
        return load_run(final_checkpoint(run_dir), device)
    except CheckpointError as err:
        raise FarRegionError(f"{run_dir}: {err}") from err


def _test_views(run: LoadedRun) -> Iterator[tuple[Any, Tensor, Tensor, Tensor, Tensor]]:
    """(camera, target [H, W, 3], image [H, W, 3] in [0, 1], alpha [H, W], depth [H, W]) of each
    test view, rendered at full SH degree on the run's background, as evaluation.py renders them."""
    model, dm = run.pipeline.model, run.pipeline.datamanager
    device = model.params["means"].device
    for i in range(len(dm.test_cameras)):
        camera, target, _ = dm.test_item(i, device)
        with torch.no_grad():
            image, alpha, depth, _ = model.render(camera, model.config.sh_degree, dm.background)
        yield camera, target, image.clamp(0.0, 1.0), alpha[..., 0].float(), depth[..., 0].float()


def far_masks(reference: Path, quantile: float = FAR_QUANTILE, device: str = "auto") -> list[Tensor]:
    """Per test view of the scene, a bool [H, W] mask (on the host) of its far pixels by the
    reference run's final model: covered (alpha >= 0.5, depth > 0) and depth >= the ``quantile``
    of depth over that view's covered pixels. One reference for every method of a scene, so all
    are judged on the same pixels."""
    quantile = check_quantile(quantile)
    run = _load_final(Path(reference), device)
    return [far_mask(alpha, depth, quantile).cpu() for _, _, _, alpha, depth in _test_views(run)]


@dataclass
class FarRegionPSNR:
    """One run's score on the far masks: pooled, per view, and how many pixels each view gave."""

    psnr: float
    """Pooled over the union of the masks of all test views (NaN: no far pixel anywhere)."""
    per_view: list[float]
    """Each test view's PSNR on its own mask (NaN where its mask is empty)."""
    pixels: list[int]
    """Far pixels of each test view."""


def far_region_psnr(run_dir: Path, masks: list[Tensor], device: str = "auto") -> FarRegionPSNR:
    """The run's final model on the test views, scored on ``masks`` (one per test view, from
    :func:`far_masks`): PSNR = -10 log10(sum of squared error / count) over all masked pixels of
    all views, floored at MSE_FLOOR, plus each view's own value."""
    run_dir = Path(run_dir)
    run = _load_final(run_dir, device)
    n_views = len(run.pipeline.datamanager.test_cameras)
    if n_views != len(masks):
        raise FarRegionError(f"{run_dir}: {n_views} test views, but the far masks are for {len(masks)}")
    total, count, per_view, pixels = 0.0, 0, [], []
    for (camera, target, image, _, _), mask in zip(_test_views(run), masks):
        if tuple(mask.shape) != tuple(image.shape[:2]):
            raise FarRegionError(f"{run_dir}: test view {camera.name} is {tuple(image.shape[:2])}, its far mask "
                                 f"{tuple(mask.shape)} (another resolution than the reference's)")
        mask = mask.to(image.device, dtype=torch.bool)
        sq, n = masked_squared_error(image, target, mask)
        total, count = total + sq, count + n
        per_view.append(psnr(image, target, mask))
        pixels.append(n)
    return FarRegionPSNR(pooled_psnr(total, count), per_view, pixels)


# ----------------------------------------------------------------------------- caches
def cached_masks(reference: Path, quantile: float, masks_file: Path | None, device: str = "auto") -> list[Tensor]:
    """:func:`far_masks`, kept in ``masks_file`` with the reference's fingerprint and the quantile
    and reused while both match (None: no file)."""
    key = {"reference": run_fingerprint(reference), "quantile": check_quantile(quantile)}
    if masks_file is not None and Path(masks_file).is_file():
        try:
            saved = torch.load(masks_file, map_location="cpu", weights_only=True)
        except Exception:  # an unreadable cache (truncated, older torch) is made again
            saved = None
        if isinstance(saved, dict) and saved.get("key") == key and isinstance(saved.get("masks"), list):
            return saved["masks"]
    masks = far_masks(reference, quantile, device)
    if masks_file is not None:
        atomic_torch_save({"key": key, "rule": describe_rule(quantile), "masks": masks}, Path(masks_file))
    return masks


def cached_far_region_psnr(run_dir: Path, reference: Path, quantile: float = FAR_QUANTILE,
                           masks: Callable[[], list[Tensor]] | None = None, device: str = "auto") -> dict[str, Any]:
    """The run's far-region PSNR as written to ``RUN/far_region.json``: reused while the reference
    (run folder, final checkpoint, step), the quantile and the run's own final checkpoint are the
    same; recomputed otherwise. ``masks``: gives the reference's masks when they are needed (by
    default :func:`far_masks` of ``reference``)."""
    run_dir, quantile = Path(run_dir), check_quantile(quantile)
    key = {"reference": run_fingerprint(reference), "quantile": quantile, "run": run_fingerprint(run_dir)}
    saved = read_json(run_dir / RESULT_NAME)
    if isinstance(saved, dict) and all(saved.get(k) == v for k, v in key.items()):
        return saved
    result = far_region_psnr(run_dir, masks() if masks is not None else far_masks(reference, quantile, device), device)
    payload = {**key, "rule": describe_rule(quantile), "psnr": result.psnr,
               "per_view": result.per_view, "pixels": result.pixels}
    write_metrics_json(run_dir / RESULT_NAME, payload)  # atomic; NaN -> null
    written = read_json(run_dir / RESULT_NAME)
    return written if isinstance(written, dict) else payload


# ----------------------------------------------------------------------------- the bench's tables
def reference_row(spec: BenchSpec, rows: list[dict[str, Any]]) -> dict[str, Any] | None:
    """The reference of a scene: the baseline entry's run at its smallest seed, when finished."""
    entry = next((e for e in spec.entries if e.name == spec.baseline), None)
    seeds = spec.seeds_of(entry) if entry is not None else ()
    if not seeds:
        return None
    return next((r for r in rows if r["entry"] == entry.name and r["seed"] == min(seeds)
                 and r["status"] == "done"), None)


def _log_stderr(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def fill_far_regions(results: Path, spec: BenchSpec, rows: list[dict[str, Any]], quantile: float = FAR_QUANTILE,
                     log: Callable[[str], None] = _log_stderr) -> None:
    """Give every finished run of a scene without region masks (a captured scene: no row has a
    ``region_far``) its far-region PSNR against the scene's reference run (:func:`reference_row`),
    in ``row["region_far"]``; ``row["far_reference"]`` names the reference, ``row["far_quantile"]``
    the quantile. Scenes without a finished reference are left as they are; a run that cannot be
    scored is logged and left empty, so one bad run folder never stops the report."""
    for scene in spec.scenes:
        mine = [r for r in rows if r["scene"] == scene.name]
        if any(r.get("region_far") is not None for r in mine):
            continue  # the scene has its own region masks
        ref = reference_row(spec, mine)
        if ref is None:
            continue
        reference = Path(ref["run_dir"])
        masks_file = Path(results) / MASKS_DIR / f"{scene.name}.pt"
        loaded: list[list[Tensor]] = []

        def masks() -> list[Tensor]:  # made (or read) once per scene, and only when a run needs them
            if not loaded:
                loaded.append(cached_masks(reference, quantile, masks_file, spec.device))
            return loaded[0]

        for row in [ref] + [r for r in mine if r is not ref and r["status"] == "done"]:
            try:
                result = cached_far_region_psnr(Path(row["run_dir"]), reference, quantile, masks, spec.device)
            except (FarRegionError, OSError, ValueError, RuntimeError) as err:
                log(f"far region of {scene.name}/{row['entry']}/seed{row['seed']}: not computed ({err})")
                if row is ref:
                    break  # the reference first: without it no run of this scene can be scored
                continue
            psnr_value = result.get("psnr")
            row["region_far"] = psnr_value if isinstance(psnr_value, (int, float)) else None
            row["far_reference"], row["far_quantile"] = f"{ref['entry']}/seed{ref['seed']}", quantile
