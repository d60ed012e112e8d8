"""The scene-count sweep's tables and claims (issue 55), from the runs of mcmc_caps.yml,
validated.yml, validated_growing.yml, validated_seedsplit.yml and second_seed_*.yml in one bench
folder:

    python experiments/scene_count/claims.py outputs/bench-count

Per scene: MCMC at each fixed cap (a multiple of Default's final count) and with a count rule:
Gaussians, test PSNR, SSIM, far-region PSNR (the bench's ``far_region.json``, written by
``eg-bench ... --report-only``), training seconds and the size of the final set as a binary 3DGS
PLY (written to a temporary folder with the project's exporter). Then the claims: the best fixed
cap, the smallest fixed cap within 0.1 dB of it (the count the scene needs), whether more was
ever worse, and for each rule whether its count is within 25% of that count and its PSNR within
0.1 dB of the best, and for each growing method with the rule its count and PSNR against the
same method without it. Entries with several seeds show their mean and each seed's PSNR. Runs that are not finished
are left out and named.
"""

from __future__ import annotations

import re
import sys
import tempfile
from pathlib import Path

from exploregs_plugin.bench.far_region import RESULT_NAME as FAR_REGION_NAME
from exploregs_plugin.bench.runner import read_json
from exploregs_plugin.io.checkpoint import load_run_checkpoint
from exploregs_plugin.io.ply import export_ply
from exploregs_plugin.engine.training_loop import METRICS_NAME

NEAR_DB = 0.1
"""A cap is as good as the best when its PSNR is within this of the best's."""
COUNT_SLACK = 0.25
"""A rule's count meets the target within this fraction of the count the scene needs."""
FIXED = re.compile(r"^mcmc(?:-x([0-9.]+))?$")
"""Entry names of the fixed caps: ``mcmc`` (1 x Default's count) and ``mcmc-xF``."""
RULES = ("mcmc-validated", "mcmc-auto")
"""Entries whose count a rule decided."""
RULED_GROWTH = (("default", "default-validated"), ("seedsplit", "seedsplit-validated"))
"""The growing methods without and with the count rule (validated_growing.yml, validated_seedsplit.yml)."""


def ply_megabytes(run_dir: Path) -> float:
    """Size in MB (10^6 bytes) of the run's final set as a binary 3DGS PLY."""
    _, _, payload = load_run_checkpoint(run_dir)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "scene.ply"
        export_ply(path, payload["params"])
        return path.stat().st_size / 1e6


def run_row(run_dir: Path) -> dict | None:
    """One finished run's figures (one seed), or None while it has no metrics."""
    m = read_json(run_dir / METRICS_NAME)
    if m is None:
        return None
    far = (read_json(run_dir / FAR_REGION_NAME) or {}).get("psnr")
    return {"gaussians": int(m["num_gaussians"]), "psnr": float(m["psnr"]), "ssim": float(m["ssim"]),
            "far": far, "train_s": float(m["train_seconds"]), "ply_mb": ply_megabytes(run_dir),
            "decision": m.get("count_decision", "")}


def scene_claims(scene_dir: Path) -> list[str]:
    lines = [f"### {scene_dir.name}", ""]
    rows, missing = {}, []
    for entry_dir in sorted(p for p in scene_dir.iterdir() if p.is_dir()):
        seeds = {d.name: run_row(d) for d in sorted(entry_dir.glob("seed*"))}
        missing += [f"{entry_dir.name}/{seed}" for seed, row in seeds.items() if row is None]
        done = [row for row in seeds.values() if row is not None]
        if done:  # the mean over the finished seeds; each seed's PSNR kept for the table
            rows[entry_dir.name] = {**done[0], **{k: sum(r[k] for r in done) / len(done)
                                                  for k in ("psnr", "ssim", "train_s", "ply_mb")},
                                    "gaussians": round(sum(r["gaussians"] for r in done) / len(done)),
                                    "far": None if any(r["far"] is None for r in done)
                                    else sum(r["far"] for r in done) / len(done),
                                    "seeds": [r["psnr"] for r in done]}
    fixed = {name: float(FIXED.match(name).group(1) or 1.0) for name in rows if FIXED.match(name)}
    lines += ["| entry | cap | Gaussians | PSNR (mean) | each seed | SSIM | far | train s | PLY MB |",
              "|---|---|---|---|---|---|---|---|---|"]
    order = sorted(fixed, key=fixed.get) + [n for n in RULES if n in rows]
    order += [n for pair in RULED_GROWTH for n in pair if n in rows]
    for name in order:
        r = rows[name]
        cap = f"{fixed[name]:g} x Default" if name in fixed else (
            "rule" if name in RULES or name.endswith("-validated") else "none")
        far = "" if r["far"] is None else f"{r['far']:.2f}"
        each = " / ".join(f"{p:.2f}" for p in r["seeds"])
        lines.append(f"| {name} | {cap} | {r['gaussians']:,} | {r['psnr']:.2f} | {each} | {r['ssim']:.4f} | {far} | "
                     f"{r['train_s']:.0f} | {r['ply_mb']:.2f} |")
    if missing:
        lines += ["", f"Not finished: {', '.join(missing)}."]
    growth = [f"- {ruled}: {rows[ruled]['gaussians']:,} Gaussians against {rows[plain]['gaussians']:,} without the "
              f"rule ({rows[ruled]['gaussians'] / rows[plain]['gaussians'] - 1.0:+.0%}), "
              f"{rows[ruled]['psnr'] - rows[plain]['psnr']:+.2f} dB"
              for plain, ruled in RULED_GROWTH if plain in rows and ruled in rows]
    if len(fixed) < 2:
        return lines + [""] + growth + ([""] if growth else [])
    best = max(fixed, key=lambda n: rows[n]["psnr"])
    near = [n for n in fixed if rows[n]["psnr"] >= rows[best]["psnr"] - NEAR_DB]
    needed = min(near, key=lambda n: rows[n]["gaussians"])
    largest = max(fixed, key=fixed.get)
    worse = rows[largest]["psnr"] < rows[best]["psnr"] - NEAR_DB
    psnrs = [rows[n]["psnr"] for n in fixed]
    n_seeds = min(len(rows[n]["seeds"]) for n in fixed)
    lines += ["", f"- {n_seeds} seed(s) per cap: the caps' mean PSNR spans {max(psnrs) - min(psnrs):.2f} dB; a count "
                  f"effect smaller than the runs' own spread is not measured;",
              f"- best fixed cap: {best}, {rows[best]['gaussians']:,} Gaussians, {rows[best]['psnr']:.2f} dB;",
              f"- the count the scene needs (smallest fixed cap within {NEAR_DB} dB of it): {needed}, "
              f"{rows[needed]['gaussians']:,} Gaussians;",
              f"- more is worse: {'yes' if worse else 'no'} ({largest}, {rows[largest]['gaussians']:,} Gaussians, "
              f"{rows[largest]['psnr'] - rows[best]['psnr']:+.2f} dB against the best)"
              + (";" if any(n in rows for n in RULES) else ".")]
    for rule in (n for n in RULES if n in rows):
        r, n_needed = rows[rule], rows[needed]["gaussians"]
        off = r["gaussians"] / n_needed - 1.0
        gap = r["psnr"] - rows[best]["psnr"]
        count_ok, psnr_ok = abs(off) <= COUNT_SLACK, gap >= -NEAR_DB
        lines.append(f"- {rule}: {r['gaussians']:,} Gaussians ({off:+.0%} against {n_needed:,}: "
                     f"{'met' if count_ok else 'missed'}), {gap:+.2f} dB against the best "
                     f"({'met' if psnr_ok else 'missed'})")
    return lines + growth + [""]


def main(argv: list[str]) -> int:
    out = Path(argv[0] if argv else "outputs/bench-count")
    runs = out / "runs"
    if not runs.is_dir():
        print(f"claims.py: {runs} is not a folder: give the bench folder of mcmc_caps.yml", file=sys.stderr)
        return 2
    for scene_dir in sorted(p for p in runs.iterdir() if p.is_dir()):
        print("\n".join(scene_claims(scene_dir)))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
