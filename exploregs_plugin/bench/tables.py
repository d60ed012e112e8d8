"""From run records to numbers (per run, per method and scene, paired against the baseline) and
to results.md / results.csv / summary.csv / results.json."""

from __future__ import annotations

import csv
import io
import json
import math
from pathlib import Path
from typing import Any

from exploregs_plugin.bench.far_region import describe_rule, fill_far_regions
from exploregs_plugin.bench.runner import RunRecord
from exploregs_plugin.bench.spec import BenchSpec
from exploregs_plugin.bench.time_quality import markdown_lines, time_to_quality
from exploregs_plugin.io.atomic import atomic_write_text

REGIONS = ("far", "occluded", "other", "moving")
"""Regions of the region masks; ``moving`` only in dynamic scenes (occluded there: by motion)."""
QUALITY = ("psnr", "ssim", "ms_ssim", "dssim", "lpips")
COST = ("num_gaussians", "train_seconds", "seconds_per_step", "render_seconds_per_image")
METRICS = (QUALITY + tuple(f"region_{r}" for r in REGIONS) + tuple(f"region_dssim_{r}" for r in REGIONS)
           + COST)
"""Every per-run number the tables use (region PSNR as ``region_far``, region D-SSIM as
``region_dssim_far`` ...)."""


def _number(value: Any) -> float | None:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None
    return value if math.isfinite(value) else None


def run_row(spec: BenchSpec, record: RunRecord) -> dict[str, Any]:
    """One run's numbers, straight from its metrics.json (None where absent)."""
    m = record.metrics or {}
    regions = m.get("region_psnr") or {}
    row: dict[str, Any] = {
        "scene": record.scene, "entry": record.entry, "method": spec.entry(record.entry).method,
        "seed": record.seed, "status": record.status, "error": record.error, "steps": m.get("steps"),
        "attempts": record.attempts, "run_dir": str(record.run_dir),
    }
    for key in QUALITY + COST:
        row[key] = _number(m.get(key))
    dssim = m.get("region_dssim") or {}
    for r in REGIONS:
        row[f"region_{r}"] = _number(regions.get(r))
        row[f"region_dssim_{r}"] = _number(dssim.get(r))
    return row


def mean_std(values: list[float]) -> dict[str, Any]:
    """Mean and sample standard deviation (ddof 1; None for fewer than two values)."""
    n = len(values)
    if n == 0:
        return {"mean": None, "std": None, "n": 0}
    mean = sum(values) / n
    std = math.sqrt(sum((v - mean) ** 2 for v in values) / (n - 1)) if n > 1 else None
    return {"mean": mean, "std": std, "n": n}


def summarize(spec: BenchSpec, rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per (scene, entry): counts, mean/std of every metric over seeds, and the paired difference
    to the baseline entry over the seeds where both finished."""
    index = {(r["scene"], r["entry"], r["seed"]): r for r in rows}
    out = []
    for scene in spec.scenes:
        for entry in spec.entries:
            seeds = spec.seeds_of(entry)
            mine = [index[(scene.name, entry.name, s)] for s in seeds if (scene.name, entry.name, s) in index]
            done = [r for r in mine if r["status"] == "done"]
            item: dict[str, Any] = {
                "scene": scene.name, "entry": entry.name, "method": entry.method,
                "n_done": len(done), "n_failed": sum(r["status"] == "failed" for r in mine),
                "n_seeds": len(seeds), "metrics": {}, "paired": {},
            }
            for key in METRICS:
                item["metrics"][key] = mean_std([r[key] for r in done if r[key] is not None])
            has_base = any(e.name == spec.baseline for e in spec.entries)
            if has_base and entry.name != spec.baseline:
                for key in METRICS:
                    diffs = []
                    for r in done:
                        base = index.get((scene.name, spec.baseline, r["seed"]))
                        if base and base["status"] == "done" and r[key] is not None and base[key] is not None:
                            diffs.append(r[key] - base[key])
                    item["paired"][key] = mean_std(diffs)
            out.append(item)
    return out


# ----------------------------------------------------------------------------- formatting
def fmt(stat: dict[str, Any], digits: int, scale: float = 1.0, signed: bool = False) -> str:
    if stat["mean"] is None:
        return "n/a"
    sign = "+" if signed else ""
    text = f"{stat['mean'] * scale:{sign}.{digits}f}"
    if stat["std"] is not None:
        text += f" ± {stat['std'] * scale:.{digits}f}"
    return text


def _cell(item: dict[str, Any], key: str, digits: int, scale: float = 1.0, paired: bool = False) -> str:
    if item["n_done"] == 0:
        return "failed" if item["n_failed"] else "—"
    stat = (item["paired"] if paired else item["metrics"]).get(key)
    if stat is None:
        return "—"
    text = fmt(stat, digits, scale, signed=paired)
    if item["n_done"] < item["n_seeds"] and text != "n/a":
        text += f" ({item['n_done']}/{item['n_seeds']})"
    return text


def _table(header: list[str], rows: list[list[str]]) -> list[str]:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    return lines + ["| " + " | ".join(r) + " |" for r in rows]


Column = tuple[str, str, int, float, bool]
"""(label, metric key, digits, scale, paired difference?)"""


def _grouped(spec: BenchSpec, summary: list[dict[str, Any]], columns: list[Column],
             scenes: list[str] | None = None, extra: dict[str, list[Column]] | None = None) -> list[str]:
    """Rows: entries; per scene one column per ``columns`` item, plus ``extra[scene]``."""
    by = {(s["scene"], s["entry"]): s for s in summary}
    scenes = scenes if scenes is not None else [s.name for s in spec.scenes]
    per_scene = {sc: columns + (extra or {}).get(sc, []) for sc in scenes}
    header = ["method"] + [f"{sc} {label}" for sc in scenes for label, *_ in per_scene[sc]]
    rows = []
    for entry in spec.entries:
        row = [entry.name]
        for sc in scenes:
            item = by[(sc, entry.name)]
            for _, key, digits, scale, paired in per_scene[sc]:
                if paired and entry.name == spec.baseline:
                    row.append("(baseline)")
                else:
                    row.append(_cell(item, key, digits, scale, paired))
        rows.append(row)
    return _table(header, rows)


def markdown(spec: BenchSpec, rows: list[dict[str, Any]], summary: list[dict[str, Any]],
             command: str | None = None, quality_times: list[str] | None = None) -> str:
    seeds = ", ".join(str(s) for s in spec.seeds)
    base = spec.baseline
    lines = [f"# Benchmark: {spec.name}", ""]
    if command:
        lines += ["```bash", command, "```", ""]
    lines += [
        f"{spec.steps} steps per run, seeds {seeds}; cells are mean ± sample std over seeds "
        f"(no ± with one seed); `(k/n)` marks cells where only k of n seeds finished. Δ is the paired "
        f"difference to `{base}` on the same scene and seed, mean ± std over seeds. LPIPS is n/a when "
        f"the runs could not compute it (no pretrained weights).",
        "",
        "## Entries", "",
    ]
    own_seeds = any(e.seeds is not None for e in spec.entries)  # a seeds column only when they differ
    lines += _table(["name", "method", "overrides", "what"] + (["seeds"] if own_seeds else []),
                    [[e.name, e.method, f"`{' '.join(e.overrides)}`" if e.overrides else "", e.description]
                     + ([", ".join(map(str, spec.seeds_of(e)))] if own_seeds else [])
                     for e in spec.entries])
    lines += ["", "Scenes: " + "; ".join(
        f"`{s.name}` = `{s.data}`" + (f" `{' '.join(s.options)}`" if s.options else "") for s in spec.scenes), ""]
    has_base = any(e.name == base for e in spec.entries)
    lines += ["## Test image quality", ""]
    lines += _grouped(spec, summary, [("PSNR", "psnr", 2, 1.0, False), ("SSIM", "ssim", 4, 1.0, False),
                                      ("D-SSIM", "dssim", 4, 1.0, False), ("LPIPS", "lpips", 4, 1.0, False)]
                      + ([("ΔPSNR", "psnr", 2, 1.0, True)] if has_base else []))
    lines += ["", "D-SSIM = (1 - MS-SSIM) / 2, as the dynamic-scene papers report it (MS-SSIM with "
              "fewer scales on small images; docs/dynamic.md)."]
    region_scenes = [s.name for s in spec.scenes
                     if any(r["scene"] == s.name and r["region_far"] is not None for r in rows)]
    regions = [g for g in REGIONS if any(r[f"region_{g}"] is not None for r in rows)]
    lines += ["", "## Paired differences to " + f"`{base}`", ""]
    region_deltas: list[Column] = [(f"Δ{r}", f"region_{r}", 2, 1.0, True) for r in regions]
    if has_base:
        lines += _grouped(spec, summary, [("ΔPSNR", "psnr", 2, 1.0, True), ("ΔSSIM", "ssim", 4, 1.0, True)],
                          extra={sc: region_deltas for sc in region_scenes})
    else:
        lines += [f"No entry named `{base}` in this bench (set another with --baseline)."]
    lines += ["", f"## Region PSNR (dB; {' / '.join(regions) or 'no regions'}, pooled over test views)", ""]
    if region_scenes:
        lines += _grouped(spec, summary, [(r, f"region_{r}", 2, 1.0, False) for r in regions], region_scenes)
        depth_far = sorted({(r["scene"], r["far_reference"], r["far_quantile"])
                            for r in rows if r.get("far_reference")})
        if depth_far:  # captured scenes: far_region.fill_far_regions
            refs = ", ".join(f"`{sc}`: `{ref}`" for sc, ref, _ in depth_far)
            lines += ["", f"For captured scenes \"far\" is {describe_rule(depth_far[0][2])} (reference run {refs}; "
                      f"the same pixels for every method)."]
        if "moving" in regions:  # a dynamic scene: occluded means occluded by motion
            lines += ["", "## Region D-SSIM (dynamic scenes; occluded = static content that moving things "
                      "cover part of the time)", ""]
            lines += _grouped(spec, summary, [(r, f"region_dssim_{r}", 4, 1.0, False) for r in regions]
                              + ([(f"Δ{r}", f"region_dssim_{r}", 4, 1.0, True) for r in regions] if has_base else []),
                              region_scenes)
    else:
        lines += ["No scene of this bench has region masks."]
    lines += ["", "## Gaussians, training time, render time", "",
              "Training seconds exclude evaluation; render time is per test image at the end."]
    lines += [""] + _grouped(spec, summary, [("Gaussians", "num_gaussians", 0, 1.0, False),
                                             ("train s", "train_seconds", 1, 1.0, False),
                                             ("render ms", "render_seconds_per_image", 1, 1000.0, False)])
    if quality_times:
        lines += ["", "## Time to quality", "", TIME_TO_QUALITY_NOTE, ""] + quality_times
    failed = [r for r in rows if r["status"] == "failed"]
    missing = [r for r in rows if r["status"] == "missing"]
    lines += ["", "## Runs", "",
              f"{len(rows)} runs: {sum(r['status'] == 'done' for r in rows)} finished, {len(failed)} failed, "
              f"{len(missing)} not run. Every run's folder is `runs/<scene>/<entry>/seed<k>/`."]
    if failed:
        lines += ["", "Failed runs:", ""]
        lines += _table(["scene", "method", "seed", "attempts", "error"],
                        [[r["scene"], r["entry"], str(r["seed"]), str(r["attempts"]),
                          str(r["error"]).replace("|", "\\|")] for r in failed])
    return "\n".join(lines) + "\n"


def write_csv(path: Path, records: list[dict[str, Any]], columns: list[str]) -> None:
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=columns, extrasaction="ignore")
    writer.writeheader()
    for r in records:
        writer.writerow({k: ("" if r.get(k) is None else r.get(k)) for k in columns})
    atomic_write_text(path, buffer.getvalue(), newline="")


def summary_rows(summary: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Flat rows for summary.csv: ``<metric>_mean``, ``<metric>_std``, ``d_<metric>_mean`` ..."""
    flat = []
    for s in summary:
        row = {k: s[k] for k in ("scene", "entry", "method", "n_done", "n_failed", "n_seeds")}
        for key, stat in s["metrics"].items():
            row[f"{key}_mean"], row[f"{key}_std"] = stat["mean"], stat["std"]
        for key, stat in s["paired"].items():
            row[f"d_{key}_mean"], row[f"d_{key}_std"], row[f"d_{key}_n"] = stat["mean"], stat["std"], stat["n"]
        flat.append(row)
    return flat


TIME_TO_QUALITY_NOTE = (
    "Training seconds (evaluations excluded) at the first evaluation that reaches each test PSNR; the "
    "levels are the baseline's final PSNR on the scene and 0.5 to 3 dB below it, and (Nx) is the ratio to "
    "the baseline's seconds at the same level (bench/time_quality.py).")


RUN_COLUMNS = ["scene", "entry", "method", "seed", "status", "steps", *METRICS, "attempts", "error", "run_dir"]


def write_tables(results: Path, spec: BenchSpec, records: list[RunRecord],
                 command: str | None = None) -> dict[str, Any]:
    """Write results.md, results.csv (one row per run), summary.csv (one row per method and scene)
    and results.json (spec, runs with their histories, summary) into ``results``."""
    rows = [run_row(spec, r) for r in records]
    fill_far_regions(Path(results), spec, rows)  # captured scenes: far by the reference run's depth
    summary = summarize(spec, rows)
    quality = time_to_quality(spec, records)
    quality_lines = markdown_lines(spec, quality)
    results = Path(results)
    results.mkdir(parents=True, exist_ok=True)
    atomic_write_text(results / "results.md", markdown(spec, rows, summary, command, quality_lines))
    write_csv(results / "results.csv", rows, RUN_COLUMNS)
    flat = summary_rows(summary)
    write_csv(results / "summary.csv", flat, list(dict.fromkeys(k for r in flat for k in r)))
    histories = {(r.scene, r.entry, r.seed): (r.metrics or {}).get("history", []) for r in records}
    payload = {
        "spec": {"name": spec.name, "steps": spec.steps, "seeds": list(spec.seeds), "eval_count": spec.eval_count,
                 "baseline": spec.baseline,
                 "entries": [{"name": e.name, "method": e.method, "overrides": list(e.overrides),
                              "description": e.description} for e in spec.entries],
                 "scenes": [{"name": s.name, "data": s.data, "options": list(s.options)} for s in spec.scenes]},
        "command": command,
        "runs": [{**row, "history": histories[(row["scene"], row["entry"], row["seed"])]} for row in rows],
        "summary": summary,
        "time_to_quality": quality,
        "time_to_quality_md": quality_lines,
    }
    atomic_write_text(results / "results.json", json.dumps(payload, indent=2))
    return payload
