"""PNG plots of a bench (matplotlib, Agg): test PSNR against training time per scene, final
PSNR against Gaussian count, and for dynamic scenes PSNR per test frame."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

from exploregs_plugin.bench.spec import BenchSpec


def _pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")  # files only: no display on a server
    import matplotlib.pyplot as plt

    return plt


def mean_curve(histories: list[list[dict[str, Any]]]) -> tuple[list[float], list[float]]:
    """Mean (train_seconds, psnr) over seeds at each evaluation index that every seed has.

    histories: one list of {step, train_seconds, psnr, ...} per seed (same steps across seeds)."""
    usable = [[h for h in hist if h.get("psnr") is not None] for hist in histories if hist]
    if not usable:
        return [], []
    length = min(len(h) for h in usable)
    xs = [sum(h[i]["train_seconds"] for h in usable) / len(usable) for i in range(length)]
    ys = [sum(h[i]["psnr"] for h in usable) / len(usable) for i in range(length)]
    return xs, ys


def _safe(name: str) -> str:
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in name)


def _save(fig: Any, path: Path) -> Path:
    """Lay out, write (110 dpi) and release a figure."""
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    fig.clf()
    _pyplot().close(fig)
    return path


def psnr_vs_time(payload: dict[str, Any], spec: BenchSpec, out_dir: Path) -> list[Path]:
    """One PNG per scene: a line per entry (mean over seeds), thin lines for single seeds."""
    plt = _pyplot()
    paths = []
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for scene in spec.scenes:
        fig, ax = plt.subplots(figsize=(6.4, 4.2))
        plotted = False
        for i, entry in enumerate(spec.entries):
            color = colors[i % len(colors)]
            runs = [r for r in payload["runs"] if r["scene"] == scene.name and r["entry"] == entry.name
                    and r["status"] == "done"]
            hists = [r["history"] for r in runs]
            for hist in hists if len(hists) > 1 else []:
                pts = [h for h in hist if h.get("psnr") is not None]
                ax.plot([h["train_seconds"] for h in pts], [h["psnr"] for h in pts], color=color, alpha=0.25, lw=0.8)
            xs, ys = mean_curve(hists)
            if xs:
                ax.plot(xs, ys, marker="o", ms=3, color=color, label=entry.name)
                plotted = True
        ax.set_xlabel("training time (s, evaluation excluded)")
        ax.set_ylabel("test PSNR (dB)")
        ax.set_title(f"{scene.name}: test PSNR against training time ({spec.steps} steps)")
        ax.grid(alpha=0.3)
        if plotted:
            ax.legend(fontsize=8)
        else:
            ax.text(0.5, 0.5, "no finished run", ha="center", va="center", transform=ax.transAxes)
        paths.append(_save(fig, Path(out_dir) / f"psnr_vs_time_{_safe(scene.name)}.png"))
    return paths


def psnr_vs_gaussians(payload: dict[str, Any], spec: BenchSpec, out_dir: Path) -> Path:
    """Final test PSNR against final Gaussian count: one panel per scene, one marker per run,
    an error-bar point per entry (mean ± std over seeds)."""
    plt = _pyplot()
    n = len(spec.scenes)
    fig, axes = plt.subplots(1, n, figsize=(4.6 * n, 4.0), squeeze=False)
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    summary = {(s["scene"], s["entry"]): s for s in payload["summary"]}
    for ax, scene in zip(axes[0], spec.scenes):
        for i, entry in enumerate(spec.entries):
            color = colors[i % len(colors)]
            runs = [r for r in payload["runs"] if r["scene"] == scene.name and r["entry"] == entry.name
                    and r["status"] == "done" and r["psnr"] is not None and r["num_gaussians"] is not None]
            ax.scatter([r["num_gaussians"] for r in runs], [r["psnr"] for r in runs], color=color, alpha=0.35, s=12)
            m = summary[(scene.name, entry.name)]["metrics"]
            if m["psnr"]["mean"] is not None and m["num_gaussians"]["mean"] is not None:
                ax.errorbar(m["num_gaussians"]["mean"], m["psnr"]["mean"], yerr=m["psnr"]["std"] or 0.0,
                            xerr=m["num_gaussians"]["std"] or 0.0, fmt="o", color=color, label=entry.name, capsize=3)
        ax.set_title(scene.name)
        ax.set_xlabel("Gaussians at the end")
        ax.set_ylabel("test PSNR (dB)")
        ax.grid(alpha=0.3)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=7)
    fig.suptitle(f"final test PSNR against Gaussian count ({spec.steps} steps)", fontsize=10)
    return _save(fig, Path(out_dir) / "psnr_vs_gaussians.png")


def frame_curves(metrics: list[dict[str, Any]], region: str | None = None) -> tuple[list[float], list[float]]:
    """Mean over runs of the PSNR of each test frame, by the frame's time: (times, PSNRs).
    ``region``: that region's PSNR in each frame (frames without the region are left out).
    metrics: each run's metrics.json; frames are matched by time."""
    by_time: dict[float, list[float]] = {}
    for m in metrics:
        for frame in m.get("per_image", []):
            value = frame.get("psnr") if region is None else frame.get("region_psnr", {}).get(region)
            if "time" in frame and value is not None and math.isfinite(value):
                by_time.setdefault(round(float(frame["time"]), 9), []).append(float(value))
    times = sorted(by_time)
    return times, [sum(by_time[t]) / len(by_time[t]) for t in times]


def psnr_per_frame(payload: dict[str, Any], spec: BenchSpec, out_dir: Path) -> list[Path]:
    """Dynamic scenes: test PSNR of each frame against its time, whole image and the region
    occluded by motion, a line per entry (mean over seeds). Scenes without timed frames get none."""
    plt = _pyplot()
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    paths = []
    for scene in spec.scenes:
        per_entry = {}
        for entry in spec.entries:
            runs = [r for r in payload["runs"] if r["scene"] == scene.name and r["entry"] == entry.name
                    and r["status"] == "done"]
            metrics = []
            for r in runs:
                try:
                    metrics.append(json.loads((Path(r["run_dir"]) / "metrics.json").read_text()))
                except (OSError, ValueError):
                    continue
            per_entry[entry.name] = metrics
        if not any(frame_curves(m)[0] for m in per_entry.values()):
            continue
        fig, axes = plt.subplots(1, 2, figsize=(10.0, 3.8))
        for i, (name, metrics) in enumerate(per_entry.items()):
            for ax, region in zip(axes, (None, "occluded")):
                times, values = frame_curves(metrics, region)
                if times:
                    ax.plot(times, values, marker="o", ms=2.5, color=colors[i % len(colors)], label=name)
        for ax, title in zip(axes, ("whole frame", "occluded by motion")):
            ax.set_xlabel("time of the test frame")
            ax.set_ylabel("PSNR (dB)")
            ax.set_title(f"{scene.name}: {title}")
            ax.grid(alpha=0.3)
            if ax.get_legend_handles_labels()[0]:
                ax.legend(fontsize=8)
        paths.append(_save(fig, Path(out_dir) / f"psnr_per_frame_{_safe(scene.name)}.png"))
    return paths


def write_plots(results: Path, spec: BenchSpec, payload: dict[str, Any]) -> list[Path]:
    return (psnr_vs_time(payload, spec, Path(results)) + [psnr_vs_gaussians(payload, spec, Path(results))]
            + psnr_per_frame(payload, spec, Path(results)))
