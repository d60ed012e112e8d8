"""Figures (matplotlib, Agg backend: no display needed) and the tables behind them (CSV/JSON)."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path
from typing import Any, Sequence

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

FIG_DPI = 90
BRANCH_STYLE = {
    "mean2d": ("2D mean", "tab:blue"),
    "cov": ("2D covariance", "tab:orange"),
    "sh": ("SH direction", "tab:green"),
    "total": ("total", "black"),
}


def write_csv(path: Path, rows: Sequence[dict[str, Any]]) -> Path:
    """One row per dict; the columns are the first row's keys (all rows must share them)."""
    if not rows:
        raise ValueError(f"no rows to write to {path}")
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0].keys()))
        writer.writeheader()
        writer.writerows(rows)
    return path


def write_json(path: Path, data: Any) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data, indent=2, sort_keys=False) + "\n")
    return path


def _save(fig: plt.Figure, path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=FIG_DPI, bbox_inches="tight")
    plt.close(fig)
    return path


def _positive(values: Sequence[float]) -> np.ndarray:
    """Log axes cannot show 0: zeros become NaN (a gap in the curve), not a fake tiny value."""
    arr = np.asarray(values, dtype=np.float64)
    return np.where(arr > 0, arr, np.nan)


def plot_branch_norms(rows: Sequence[dict[str, Any]], path: Path, title: str = "") -> Path:
    """Mean per-view gradient norm of each branch over iterations, log scale.

    rows: dicts with "step" and one key per branch in BRANCH_STYLE.
    """
    fig, ax = plt.subplots(figsize=(6.0, 3.8))
    steps = [r["step"] for r in rows]
    for key, (label, color) in BRANCH_STYLE.items():
        ax.plot(steps, _positive([r[key] for r in rows]), marker="o", ms=3, label=label, color=color,
                ls="--" if key == "total" else "-")  # fmt: skip
    ax.set_yscale("log")
    ax.set_xlabel("iteration")
    ax.set_ylabel("mean |dL/d$\\mu$| per view")
    ax.set_title(title or "position gradient by branch")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    return _save(fig, path)


def plot_direction_histograms(cosines: dict[str, dict[str, np.ndarray]], path: Path, bins: int = 20,
                              title: str = "") -> Path:
    """One panel per branch (rows) and reference (columns): histogram of |cos| in [0, 1]."""
    branches = list(cosines)
    refs = list(next(iter(cosines.values())))
    labels = {"ray": "camera-to-Gaussian ray", "axis": "optical axis"}
    fig, axes = plt.subplots(len(branches), len(refs), figsize=(3.2 * len(refs), 1.9 * len(branches)),
                             squeeze=False, sharex=True)  # fmt: skip
    edges = np.linspace(0.0, 1.0, bins + 1)
    for i, branch in enumerate(branches):
        for j, ref in enumerate(refs):
            ax = axes[i][j]
            values = np.asarray(cosines[branch][ref])
            weights = np.full(values.shape, 1.0 / max(len(values), 1))
            ax.hist(values, bins=edges, weights=weights, color=BRANCH_STYLE[branch][1])
            med = float(np.median(values)) if len(values) else math.nan
            ax.set_title(f"{BRANCH_STYLE[branch][0]} vs {labels.get(ref, ref)}\nn={len(values)}, median {med:.2g}",
                         fontsize=8)  # fmt: skip
            ax.tick_params(labelsize=7)
            if j == 0:
                ax.set_ylabel("fraction", fontsize=8)
            if i == len(branches) - 1:
                ax.set_xlabel("|cos|", fontsize=8)
    if title:
        fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    return _save(fig, path)


def _gradient_panel(ax: plt.Axes, x: Sequence[float], rows: Sequence[dict[str, Any]], threshold: float,
                    series: Sequence[tuple[str, str]], ylabel: str) -> None:
    """Screen-space gradients on a log axis (series: (row key, label)) and the threshold line."""
    for (key, label), marker in zip(series, ("o-", "s-")):
        ax.semilogy(x, _positive([r[key] for r in rows]), marker, ms=3, alpha=0.85, label=label)
    ax.axhline(threshold, color="red", ls="--", label=f"grow_grad2d = {threshold:g}")
    ax.set_ylabel(ylabel)
    ax.legend(fontsize=7)


def _three_panels(x: Sequence[float], rows: Sequence[dict[str, Any]], threshold: float, path: Path,
                  series: Sequence[tuple[str, str]], lower: Sequence[tuple[str, str, str, bool]], xlabel: str,
                  title: str) -> Path:
    """Gradient panel on top, then two panels (row key, y label, colour, log scale)."""
    fig, axes = plt.subplots(3, 1, figsize=(6.0, 6.5), sharex=True)
    _gradient_panel(axes[0], x, rows, threshold, series, "|dL/d$\\mu_{2D}$| (NDC)")
    for ax, (key, ylabel, color, log) in zip(axes[1:], lower):
        ax.plot(x, _positive([r[key] for r in rows]) if log else [r[key] for r in rows], "o-", ms=3, color=color)
        ax.set_ylabel(ylabel)
        if log:
            ax.set_yscale("log")
    axes[-1].set_xlabel(xlabel)
    for ax in axes:
        ax.grid(True, which="both", alpha=0.3)
    axes[0].set_title(title)
    return _save(fig, path)


def plot_pixel_blending(rows: Sequence[dict[str, Any]], threshold: float, path: Path, title: str = "") -> Path:
    """Three panels over the composited Gaussians in order: screen-space gradient (with the
    densification threshold), camera depth, transmittance before each."""
    return _three_panels(
        [r["order"] for r in rows], rows, threshold, path,
        [("grad_image", "view loss (densification statistic)"), ("grad_pixel", "through this pixel only")],
        [("depth", "camera depth z", "tab:purple", False), ("T_before", "T before", "tab:brown", True)],
        "blending order (0 = front)", title or "Gaussians composited at one pixel",
    )  # fmt: skip


def plot_rank_profile(rows: Sequence[dict[str, Any]], threshold: float, path: Path, title: str = "") -> Path:
    """Scene-wide: mean screen-space gradients, mean transmittance and pixel count against depth rank."""
    series = [("mean_grad", "whole view (densification statistic)")]
    if rows and "mean_pixel_grad" in rows[0]:
        series.append(("mean_pixel_grad", "through this pixel only"))
    return _three_panels(
        [r["rank"] for r in rows], rows, threshold, path, series,
        [("mean_T", "mean T before", "tab:brown", True), ("pixels", "pixels", "tab:gray", True)],
        "depth rank at the pixel (0 = front)", title or "by depth rank over all pixels of a view",
    )  # fmt: skip


def plot_visibility(rows: Sequence[dict[str, Any]], threshold: float, path: Path, title: str = "") -> Path:
    """Gaussians binned by their best transmittance in the view: mean screen-space gradient (with
    the threshold) and the share above the threshold, one bar per bin."""
    labels = [f"[{r['lo']:g}, {r['hi']:g})\nn={r['gaussians']}" for r in rows]
    pos = np.arange(len(rows))
    fig, axes = plt.subplots(2, 1, figsize=(6.0, 5.0), sharex=True)
    axes[0].bar(pos, _positive([r["mean_grad"] for r in rows]), color="tab:blue")
    axes[0].set_yscale("log")
    axes[0].axhline(threshold, color="red", ls="--", label=f"grow_grad2d = {threshold:g}")
    axes[0].set_ylabel("mean |dL/d$\\mu_{2D}$| (NDC)")
    axes[0].legend(fontsize=7)
    axes[1].bar(pos, [r["frac_above"] for r in rows], color="tab:gray")
    axes[1].set_ylabel("share above threshold")
    axes[1].set_ylim(0, 1)
    axes[1].set_xticks(pos, labels, fontsize=7)
    axes[1].set_xlabel("best T before the Gaussian over its pixels in this view")
    for ax in axes:
        ax.grid(True, axis="y", which="both", alpha=0.3)
    axes[0].set_title(title or "screen-space gradient against visibility")
    return _save(fig, path)
