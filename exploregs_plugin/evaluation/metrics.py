"""Test-set evaluation: PSNR, SSIM, MS-SSIM and D-SSIM per image and per region, LPIPS
(AlexNet, v0.1; :mod:`exploregs_plugin.evaluation.perceptual`) when its weights are installed, render time;
per frame (with its time) for dynamic scenes."""

from __future__ import annotations

import json
import math
import os
import time
import warnings
from pathlib import Path
from typing import Any, Callable, Iterable, Sequence

import numpy as np
import torch
from PIL import Image

from exploregs_plugin.model.losses import SSIM_WINDOW, d_ssim, ms_ssim_many, pooled_psnr, psnr, ssim_map
from exploregs_plugin.model import GaussianModel
from exploregs_plugin.io.atomic import atomic_write_text
from exploregs_plugin.evaluation.perceptual import (INSTALL_HINT, MIN_SIDE, WEIGHTS_ENV, LpipsWeightsError, lpips_available,
                                         lpips_network)

LPIPS_ABSENT = ("absent: LPIPS needs pretrained network weights, which are not available on this machine "
                f"(`{INSTALL_HINT}` installs AlexNet-LPIPS v0.1's)")
LPIPS_TOO_SMALL = f"absent: LPIPS (AlexNet) needs test images of at least {MIN_SIDE} px per side"


def lpips_absent_note() -> str:
    """Why a summary has no LPIPS: no weights (with the install hint, or what is wrong with
    ``EXPLOREGS_LPIPS_WEIGHTS`` when it is set), or test images below AlexNet's smallest input."""
    available, reason = lpips_available()
    if available:
        return LPIPS_TOO_SMALL
    return f"absent: {reason}" if os.environ.get(WEIGHTS_ENV) else LPIPS_ABSENT


def _to_uint8(img: torch.Tensor) -> np.ndarray:
    return (img.detach().clamp(0, 1).cpu().numpy() * 255.0 + 0.5).astype(np.uint8)


def error_map(render: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Per-pixel mean absolute error as a grey image [H, W, 3], scaled so 0.25 error is white."""
    err = (render - target).abs().mean(dim=-1, keepdim=True)
    return (err / 0.25).clamp(0, 1).expand(-1, -1, 3)


def evaluation_panel(image: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """render | ground truth | error map side by side: [H, 3W, 3]."""
    return torch.cat([image, target, error_map(image, target)], dim=1)


def evaluate(
    model: GaussianModel,
    datamanager: Any,
    save_dir: Path | None = None,
    on_image: Callable[[int, str, torch.Tensor, torch.Tensor], None] | None = None,
) -> dict[str, Any]:
    """Render every test view at full SH degree and score it against the ground truth.

    Image PSNR/SSIM are means over test images (the usual convention). Region PSNR pools the
    squared error over all pixels of that region in all test images, since a region can cover
    only a few pixels of one view. With ``save_dir``, writes render | ground truth | error map
    PNGs there. ``on_image(index, name, render, target)`` sees each test render as it is made
    (the trainer keeps a few for tensorboard without rendering them again; on the host).
    Renders and scores on the model's device; the targets come from the host.
    """
    part = evaluate_views(model, datamanager, range(len(datamanager.test_cameras)), save_dir, on_image)
    return summarize_evaluation([part], model.num_gaussians)


def evaluate_views(
    model: GaussianModel,
    datamanager: Any,
    views: Iterable[int],
    save_dir: Path | None = None,
    on_image: Callable[[int, str, torch.Tensor, torch.Tensor], None] | None = None,
) -> dict[str, Any]:
    """Score some of the test views (a rank's share): a part for :func:`summarize_evaluation`,
    {"per_image": [...], "region_sq": {...}, "region_ssim": {...}, "region_n": {...},
    "render_seconds": s}, picklable; with "lpips_note" when LPIPS weights were found but unreadable."""
    device = model.params["means"].device
    per_image: list[dict[str, Any]] = []
    region_sq: dict[str, float] = {}
    region_ssim: dict[str, float] = {}
    region_n: dict[str, int] = {}
    render_seconds = 0.0
    # LPIPS when its weights are installed: the network is built on the first use and cached, so
    # an evaluation without the weights costs one file lookup. Unreadable weights (a damaged file,
    # or one holding more than numpy arrays) leave LPIPS out with a warning: the other metrics of
    # a finished training run are worth more than stopping at its last step.
    lpips_net, lpips_note = None, None
    if lpips_available()[0]:
        try:
            lpips_net = lpips_network(device)
        except LpipsWeightsError as err:
            lpips_note = f"absent: the LPIPS weights could not be read: {err}"
            warnings.warn(lpips_note, stacklevel=2)
    if save_dir is not None:
        Path(save_dir).mkdir(parents=True, exist_ok=True)
    for i in views:
        camera, target, extras = datamanager.test_item(i, device)
        start = time.perf_counter()
        with torch.no_grad():
            image, _, _, _ = model.render(camera, model.config.sh_degree, datamanager.background)
        if device.type == "cuda":
            torch.cuda.synchronize(device)  # kernels run asynchronously: time the work, not the launch
        render_seconds += time.perf_counter() - start
        image = image.clamp(0.0, 1.0)
        ssim_pixels = ssim_map(image, target).mean(dim=-1)  # [H, W]
        entry: dict[str, Any] = {
            "index": i,
            "name": camera.name,
            "psnr": psnr(image, target),
            "ssim": float(ssim_pixels.mean()),
        }
        masks = extras.get("masks", {}) if isinstance(extras, dict) else {}
        region_ms_ssim: dict[str, float] = {}
        if min(image.shape[:2]) >= SSIM_WINDOW:  # the whole image and every region in one pass
            values = ms_ssim_many(image, target, [None, *(m.to(device) for m in masks.values())])
            entry["ms_ssim"] = values[0]
            entry["dssim"] = d_ssim(values[0])
            region_ms_ssim = dict(zip(masks, values[1:]))
        if lpips_net is not None and min(image.shape[:2]) >= MIN_SIDE:
            entry["lpips"] = lpips_net.distance(image, target)
        if camera.time is not None:
            entry["time"] = camera.time
        if masks:
            entry["region_psnr"], entry["region_ssim"], entry["region_ms_ssim"] = {}, {}, {}
            sq = ((image.double() - target.double()) ** 2).mean(dim=-1)
            for region, mask in masks.items():
                mask = mask.to(device)
                entry["region_psnr"][region] = psnr(image, target, mask)
                count = int(mask.sum())
                ssim_sum = float(ssim_pixels[mask].double().sum())
                entry["region_ssim"][region] = ssim_sum / count if count else float("nan")
                if region in region_ms_ssim:
                    entry["region_ms_ssim"][region] = region_ms_ssim[region]
                region_sq[region] = region_sq.get(region, 0.0) + float(sq[mask].sum())
                region_ssim[region] = region_ssim.get(region, 0.0) + ssim_sum
                region_n[region] = region_n.get(region, 0) + count
        per_image.append(entry)
        if on_image is not None:
            on_image(i, camera.name, image.cpu(), target.cpu())
        if save_dir is not None:
            panel = evaluation_panel(image, target)
            Image.fromarray(_to_uint8(panel)).save(Path(save_dir) / f"{i:04d}_{Path(camera.name).stem}.png")
    part: dict[str, Any] = {"per_image": per_image, "region_sq": region_sq, "region_ssim": region_ssim,
                            "region_n": region_n, "render_seconds": render_seconds}
    if lpips_note is not None:
        part["lpips_note"] = lpips_note
    return part


def summarize_evaluation(parts: Sequence[dict[str, Any]], num_gaussians: int) -> dict[str, Any]:
    """The metrics of the test views scored in ``parts`` (the ranks' shares, in any order).

    Image metrics are means over the test images; LPIPS over those it could score (it is None,
    with ``lpips_note`` saying why, when it scored none). Region PSNR and SSIM pool all pixels of the
    region in all test images (a region may cover a few pixels of one view); region MS-SSIM is
    the mean over the images where the region has a window at every scale. D-SSIM is
    (1 - MS-SSIM) / 2, the dynamic-scene convention."""
    per_image = sorted((entry for part in parts for entry in part["per_image"]), key=lambda e: e["index"])
    region_sq: dict[str, float] = {}
    region_ssim: dict[str, float] = {}
    region_n: dict[str, int] = {}
    for part in parts:
        for region, value in part["region_sq"].items():
            region_sq[region] = region_sq.get(region, 0.0) + value
            region_ssim[region] = region_ssim.get(region, 0.0) + part.get("region_ssim", {}).get(region, 0.0)
            region_n[region] = region_n.get(region, 0) + part["region_n"][region]
    n_test = len(per_image)

    def mean(key: str) -> float:
        values = [e[key] for e in per_image if key in e]
        return float(np.mean(values)) if values else float("nan")

    lpips_values = [e["lpips"] for e in per_image if "lpips" in e]
    lpips_info: dict[str, Any] = {"lpips": float(np.mean(lpips_values)) if lpips_values else None}
    if not lpips_values:
        notes = [part["lpips_note"] for part in parts if "lpips_note" in part]
        lpips_info["lpips_note"] = notes[0] if notes else lpips_absent_note()
    elif len(lpips_values) < n_test:
        lpips_info["lpips_note"] = (f"mean over {len(lpips_values)} of {n_test} test images; the others are "
                                    f"smaller than {MIN_SIDE} px per side (AlexNet's smallest input)")
    result: dict[str, Any] = {
        "num_test_images": n_test,
        "psnr": mean("psnr"),
        "ssim": mean("ssim"),
        "ms_ssim": mean("ms_ssim"),
        "dssim": mean("dssim"),
        **lpips_info,
        "num_gaussians": num_gaussians,
        "render_seconds_per_image": sum(part["render_seconds"] for part in parts) / max(n_test, 1),
        "per_image": [{k: v for k, v in e.items() if k != "index"} for e in per_image],
    }
    if region_n:
        result["region_psnr"] = {
            r: pooled_psnr(region_sq[r], region_n[r]) for r in sorted(region_n)
        }
        result["region_ssim"] = {r: (region_ssim[r] / region_n[r] if region_n[r] else float("nan"))
                                 for r in sorted(region_n)}
        result["region_ms_ssim"] = {}
        for r in sorted(region_n):
            values = [e["region_ms_ssim"][r] for e in per_image if r in e.get("region_ms_ssim", {})]
            finite = [v for v in values if math.isfinite(v)]
            result["region_ms_ssim"][r] = float(np.mean(finite)) if finite else float("nan")
        result["region_dssim"] = {r: d_ssim(v) for r, v in result["region_ms_ssim"].items()}
        result["region_pixels"] = dict(sorted(region_n.items()))
    return result


def _finite_or_none(value: Any) -> Any:
    """JSON has no NaN/inf: write them as null."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _finite_or_none(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_finite_or_none(v) for v in value]
    return value


def write_metrics_json(path: Path, metrics: dict[str, Any]) -> None:
    """Write metrics as JSON atomically (temporary file, then rename); NaN/inf become null."""
    atomic_write_text(path, json.dumps(_finite_or_none(metrics), indent=2))
