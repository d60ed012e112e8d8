"""Threads beside busy processes: training time at the default thread count and at one thread.

    python -m exploregs_plugin.bench.components.threads                         # 150 steps of builtin:default
    python -m exploregs_plugin.bench.components.threads --cpus 0 1 --repeats 3  # on two CPUs of a larger machine

Each run trains ``--method`` on ``--data`` for ``--steps`` steps in a fresh ``eg-train`` process
(quiet, no tensorboard, one evaluation, no saved images), at the default thread count (which
follows the CPUs other processes leave idle) and with ``--num-threads 1``, beside 0, 1 and 2
competitors (``--competitors``): processes that keep one CPU busy each (``python -c "while True:
pass"``), started a second before the run and stopped after it. The two settings of a pair run
back to back, their order alternating between repeats. ``--cpus`` pins the runs and the
competitors to those CPUs (a two-core machine on a larger one). A first short run, not timed,
builds the compiled kernels and the scene.

The table gives, per number of competitors, the median training seconds of each setting
(``train_seconds`` of metrics.json: the steps alone, start-up and evaluation excluded), the thread
counts the default trained with (metrics.json's ``threads``), and the ratio default / one thread
(issue 48's goal: at most 1.1). The numbers mean something only on a machine without other work.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Callable

SETTINGS = {"default": [], "one thread": ["--num-threads", "1"]}
COMPETITOR = "while True: pass"


def _pinned(cpus: list[int] | None) -> Callable[[], None] | None:
    return None if not cpus else (lambda: os.sched_setaffinity(0, set(cpus)))


def train_once(args: argparse.Namespace, run_dir: Path, extra: list[str], steps: int) -> dict[str, Any]:
    """One eg-train run in a fresh process; its metrics.json."""
    argv = [sys.executable, "-m", "exploregs_plugin.scripts.train", args.method, "--data", args.data,
            "--max-steps", str(steps), "--run-dir", str(run_dir), "--quiet", "--no-tensorboard",
            "--no-save-eval-images", "--eval-count", "1", *extra]
    env = {k: v for k, v in os.environ.items() if k != "OMP_NUM_THREADS"}  # the default must choose
    done = subprocess.run(argv, env=env, capture_output=True, text=True, preexec_fn=_pinned(args.cpus))
    if done.returncode != 0:
        raise RuntimeError(f"eg-train failed ({done.returncode}): {done.stderr.strip()[-2000:]}")
    return json.loads((run_dir / "metrics.json").read_text())


def beside_competitors(count: int, cpus: list[int] | None, run: Callable[[], dict[str, Any]]) -> dict[str, Any]:
    """``run()`` while ``count`` processes keep a CPU busy each."""
    busy = [subprocess.Popen([sys.executable, "-c", COMPETITOR], preexec_fn=_pinned(cpus)) for _ in range(count)]
    try:
        time.sleep(1.0)  # they spin before the run measures the idle CPUs
        return run()
    finally:
        for proc in busy:
            proc.kill()
            proc.wait()


def table(rows: list[dict[str, Any]]) -> str:
    """Markdown: per competitor count, the median training seconds of each setting, the default's
    thread counts and the ratio default / one thread. rows: competitors, setting, seconds, threads."""
    lines = ["| busy processes | default (s) | default's threads | one thread (s) | default / one thread |",
             "|---|---|---|---|---|"]
    for count in sorted({row["competitors"] for row in rows}):
        mine = [row for row in rows if row["competitors"] == count]
        median = {name: statistics.median(r["seconds"] for r in mine if r["setting"] == name) for name in SETTINGS}
        threads = sorted({t for r in mine if r["setting"] == "default" for t in r["threads"]})
        spread = {name: [r["seconds"] for r in mine if r["setting"] == name] for name in SETTINGS}
        cells = [f"{median[name]:.2f} ({min(spread[name]):.2f}-{max(spread[name]):.2f})" for name in SETTINGS]
        ratio = median["default"] / max(median["one thread"], 1e-9)
        lines.append(f"| {count} | {cells[0]} | {threads} | {cells[1]} | {ratio:.2f} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", default="builtin:default")
    parser.add_argument("--method", default="exploregs-default")
    parser.add_argument("--steps", type=int, default=150)
    parser.add_argument("--competitors", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--repeats", type=int, default=2, help="pairs per competitor count (order alternates)")
    parser.add_argument("--cpus", type=int, nargs="*", default=None, help="pin everything to these CPUs")
    parser.add_argument("--out", type=Path, default=None, help="keep the runs here (default: a temporary folder)")
    args = parser.parse_args(argv)
    load = os.getloadavg()[0]  # other work on the machine: the figures need it near 0
    rows: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory() as tmp:
        folder = args.out or Path(tmp)
        train_once(args, folder / "warm-up", [], 2)
        for count in args.competitors:
            for repeat in range(args.repeats):
                names = list(SETTINGS) if repeat % 2 == 0 else list(reversed(SETTINGS))
                for name in names:
                    run_dir = folder / f"busy{count}-{repeat}-{name.replace(' ', '-')}"
                    metrics = beside_competitors(count, args.cpus,
                                                 lambda: train_once(args, run_dir, SETTINGS[name], args.steps))
                    rows.append({"competitors": count, "setting": name, "seconds": metrics["train_seconds"],
                                 "threads": metrics["threads"]})
                    print(f"{count} busy, {name}: {metrics['train_seconds']:.1f} s training, threads "
                          f"{metrics['threads']}", file=sys.stderr, flush=True)
    cpus = args.cpus or sorted(os.sched_getaffinity(0))
    print(f"{args.method} on {args.data}, {args.steps} steps, CPUs {cpus}, load average before the runs {load:.2f}")
    print(table(rows))


if __name__ == "__main__":
    main()
