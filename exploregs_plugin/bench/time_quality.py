"""Time to quality: the training seconds each entry needs to reach given test PSNRs.

Every run records a point of its PSNR-against-time curve at each periodic evaluation
(``metrics.json`` ``history``: the step, ``train_seconds`` and the test ``psnr``), and the trainer
stops its training clock while it evaluates, so the seconds are training alone. The time to a
PSNR level is the training time at the first evaluation whose PSNR reaches the level: an upper
bound, within one evaluation interval of the crossing (the bench's ``eval_count`` sets the
interval). The levels are the baseline's final PSNR on the scene (mean over seeds) minus
:data:`LEVELS_BELOW_BASELINE` dB, so every entry is timed to the qualities today's default
reaches; a ratio is the entry's time over the baseline's at the same level.
"""

from __future__ import annotations

from typing import Any

from exploregs_plugin.bench.runner import RunRecord
from exploregs_plugin.bench.spec import BenchSpec

LEVELS_BELOW_BASELINE = (3.0, 2.0, 1.0, 0.5, 0.0)
"""The PSNR levels, in dB below the baseline's final PSNR on the scene."""


def seconds_to_reach(history: list[dict[str, Any]], level: float) -> float | None:
    """Training seconds at the first evaluation whose test PSNR is at least ``level``; None
    when no evaluation reaches it. ``history``: a run's evaluations in step order."""
    for point in sorted(history, key=lambda p: p["step"]):
        psnr = point.get("psnr")
        if psnr is not None and psnr >= level:
            return float(point["train_seconds"])
    return None


def _mean(values: list[float]) -> float | None:
    return sum(values) / len(values) if values else None


def time_to_quality(spec: BenchSpec, records: list[RunRecord],
                    below: tuple[float, ...] = LEVELS_BELOW_BASELINE) -> list[dict[str, Any]]:
    """Per scene and entry: the levels (dB), the mean training seconds to each over the seeds
    (None unless every finished seed reached it), the ratio to the baseline's, and the final PSNR,
    Gaussian count and training seconds (means over the finished seeds). A scene without a
    finished baseline run has no levels (its rows have none)."""
    done: dict[tuple[str, str], list[dict[str, Any]]] = {}
    for record in records:
        if record.status == "done" and record.metrics:
            done.setdefault((record.scene, record.entry), []).append(record.metrics)
    rows = []
    for scene in spec.scenes:
        base_final = _mean([m["psnr"] for m in done.get((scene.name, spec.baseline), [])])
        levels = [] if base_final is None else [base_final - d for d in below]
        base_seconds = _seconds(done.get((scene.name, spec.baseline), []), levels)
        for entry in spec.entries:
            runs = done.get((scene.name, entry.name), [])
            seconds = _seconds(runs, levels)
            ratios = [None if s is None or b is None or b <= 0 else s / b for s, b in zip(seconds, base_seconds)]
            rows.append({
                "scene": scene.name, "entry": entry.name, "n_done": len(runs), "levels": levels,
                "seconds": seconds, "ratios": ratios,
                "psnr": _mean([m["psnr"] for m in runs]),
                "num_gaussians": _mean([m["num_gaussians"] for m in runs]),
                "train_seconds": _mean([m["train_seconds"] for m in runs]),
                "base_train_seconds": None if not base_seconds else _mean(
                    [m["train_seconds"] for m in done.get((scene.name, spec.baseline), [])]),
            })
    return rows


def _seconds(runs: list[dict[str, Any]], levels: list[float]) -> list[float | None]:
    """Mean seconds to each level over ``runs``; None for a level some run never reached."""
    out: list[float | None] = []
    for level in levels:
        reached = [seconds_to_reach(m.get("history", []), level) for m in runs]
        out.append(None if not reached or any(s is None for s in reached) else _mean(reached))  # type: ignore[arg-type]
    return out


def markdown_lines(spec: BenchSpec, rows: list[dict[str, Any]],
                   below: tuple[float, ...] = LEVELS_BELOW_BASELINE) -> list[str]:
    """The time-to-quality tables, one per scene: for each entry the training seconds to each
    level with its ratio to the baseline's (`12.3 s (0.52x)`; `not reached`), the final PSNR,
    the Gaussian count and the training seconds with their ratio."""
    lines: list[str] = []
    for scene in spec.scenes:
        mine = [r for r in rows if r["scene"] == scene.name]
        if not mine or not mine[0]["levels"]:
            lines += [f"`{scene.name}`: no finished `{spec.baseline}` run, so no levels.", ""]
            continue
        levels = mine[0]["levels"]
        header = ["method"] + [f"s to {lv:.2f} dB" + (f" (-{d:g})" if d else " (base)") for lv, d in zip(levels, below)]
        header += ["final PSNR", "Gaussians", "train s"]
        table = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
        for r in mine:
            if r["n_done"] == 0:
                table.append("| " + " | ".join([r["entry"]] + ["—"] * (len(header) - 1)) + " |")
                continue
            cells = [r["entry"]]
            for seconds, ratio in zip(r["seconds"], r["ratios"]):
                cells.append("not reached" if seconds is None else
                             f"{seconds:.1f}" + ("" if ratio is None else f" ({ratio:.2f}x)"))
            total_ratio = (None if not r["base_train_seconds"] or r["train_seconds"] is None
                           else r["train_seconds"] / r["base_train_seconds"])
            cells += [f"{r['psnr']:.2f}", f"{r['num_gaussians']:.0f}",
                      f"{r['train_seconds']:.1f}" + ("" if total_ratio is None else f" ({total_ratio:.2f}x)")]
            table.append("| " + " | ".join(cells) + " |")
        lines += [f"`{scene.name}`:", ""] + table + [""]
    return lines
