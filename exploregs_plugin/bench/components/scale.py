"""Data-parallel scaling and batched views: images per second and PSNR at equal images seen.

    python -m exploregs_plugin.bench.components.scale --data builtin:default --images 1500 --ranks 1 2
    python -m exploregs_plugin.bench.components.scale --batches 1 2 4 8 --device cuda --threads 4

Each row is one ``eg-train`` run (a fresh process, so nothing is shared between rows) that sees
about ``--images`` training images: ``round(images / B)`` steps of B views (the table gives the
exact count). With ``--out``, finished runs there are read again instead of retrained. Rows with R ranks launch them with
``--machine.num-devices R``, one view per rank (B = R) unless ``--batches`` says otherwise; every
rank gets ``--threads`` CPU threads, so R ranks use R x threads cores. Throughput is images seen
per second of the run's training time (rank 0's loop, which waits for the slowest rank).

The baseline is the first row (1 rank, B = 1) of the same invocation:
``speedup = ips / ips(baseline)``, ``efficiency = speedup / R`` (ideal 1.0 when R ranks have R
times the cores), and ``dPSNR`` is the test PSNR against the baseline's, seed for seed.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any


def run_row(data: str, method: str, images: int, ranks: int, batch: int, seed: int, threads: int, device: str,
            data_factor: int | None, extra: list[str], folder: Path) -> dict[str, Any]:
    """Train one configuration in a fresh eg-train process and return its metrics. A finished
    run of the same configuration in ``folder`` is read instead of trained again."""
    steps = max(1, round(images / batch))  # B views per step: about the same images at every B
    run_dir = folder / f"r{ranks}-b{batch}-s{seed}-i{steps * batch}"
    argv = [sys.executable, "-m", "exploregs_plugin.scripts.train", method, "--data", data,
            "--max-steps", str(steps), "--batch-size", str(batch), "--seed", str(seed),
            "--run-dir", str(run_dir), "--quiet", "--no-tensorboard", "--no-save-eval-images", "--eval-count", "1",
            "--num-threads", str(threads), "--device", device, "--machine.num-devices", str(ranks), *extra]
    if data_factor is not None:
        argv += ["--data-factor", str(data_factor)]
    metrics_file = run_dir / "metrics.json"
    if not metrics_file.exists():
        env = dict(os.environ, OMP_NUM_THREADS=str(threads))
        done = subprocess.run(argv, env=env, capture_output=True, text=True)
        if done.returncode != 0:
            raise RuntimeError(f"eg-train failed (ranks {ranks}, batch {batch}, seed {seed}):\n{done.stderr[-2000:]}")
    metrics = json.loads(metrics_file.read_text())
    seen = steps * batch
    return {"ranks": ranks, "batch": batch, "seed": seed, "steps": steps, "images": seen,
            "train_seconds": metrics["train_seconds"], "ips": seen / metrics["train_seconds"],
            "psnr": metrics["psnr"], "gaussians": metrics["num_gaussians"]}


def table(rows: list[dict[str, Any]]) -> str:
    """Markdown table, one line per (ranks, batch), means over seeds; ratios against the first."""
    groups: dict[tuple[int, int], list[dict[str, Any]]] = {}
    for row in rows:
        groups.setdefault((row["ranks"], row["batch"]), []).append(row)
    base_key = next(iter(groups))
    base_ips = statistics.mean(r["ips"] for r in groups[base_key])
    base_psnr = {r["seed"]: r["psnr"] for r in groups[base_key]}
    lines = ["| ranks | B | steps | images | images/s | speedup | efficiency | PSNR | dPSNR (paired) | Gaussians |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for (ranks, batch), group in groups.items():
        ips = statistics.mean(r["ips"] for r in group)
        deltas = [r["psnr"] - base_psnr[r["seed"]] for r in group if r["seed"] in base_psnr]
        spread = f" ± {statistics.stdev(deltas):.2f}" if len(deltas) > 1 else ""
        lines.append(
            f"| {ranks} | {batch} | {group[0]['steps']} | {group[0]['images']} | {ips:.2f} | {ips / base_ips:.2f} | "
            f"{ips / base_ips / ranks:.2f} | {statistics.mean(r['psnr'] for r in group):.2f} | "
            f"{statistics.mean(deltas):+.2f}{spread} | {statistics.mean(r['gaussians'] for r in group):,.0f} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", default="builtin:default")
    parser.add_argument("--data-factor", type=int, default=None)
    parser.add_argument("--method", default="exploregs-seedsplit")
    parser.add_argument("--images", type=int, default=1200, help="training images seen by every row")
    parser.add_argument("--ranks", type=int, nargs="+", default=[1, 2], help="ranks per row (one view each)")
    parser.add_argument("--batches", type=int, nargs="*", default=[],
                        help="also rows of one rank with these batch sizes")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0])
    parser.add_argument("--threads", type=int, default=1, help="CPU threads per rank")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--out", type=Path, default=None, help="keep the runs here (default: a temporary folder)")
    parser.add_argument("extra", nargs=argparse.REMAINDER, help="more eg-train arguments after --")
    args = parser.parse_args(argv)
    extra = args.extra[1:] if args.extra[:1] == ["--"] else args.extra
    layouts = [(1, 1)] + [(r, r) for r in args.ranks if r != 1] + [(1, b) for b in args.batches if b != 1]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        folder = args.out or Path(tmp)
        for ranks, batch in layouts:
            for seed in args.seeds:
                row = run_row(args.data, args.method, args.images, ranks, batch, seed, args.threads, args.device,
                              args.data_factor, extra, folder)
                rows.append(row)
                print(f"ranks {ranks} B {batch} seed {seed}: {row['ips']:.2f} images/s, PSNR {row['psnr']:.2f}",
                      file=sys.stderr, flush=True)
    print(f"{args.method} on {args.data}, {args.images} images per run, {args.threads} thread(s) per rank, "
          f"device {args.device}, {os.cpu_count()} cores")
    print(table(rows))


if __name__ == "__main__":
    main()
