"""The summary of one GPU comparison (gpu_comparison.sh), read from each trainer's own files:

    python experiments/gpu/summary.py WORK OUT STEPS "PARTS" "C_ARGS" "C2_ARGS"

WORK holds the runs (st-default, st-seedsplit: gsplat's simple_trainer; eg-train, eg-train-2:
ours) and the wall seconds of each part (times/NAME); OUT holds the logs. Printed: (a)'s ratio
table, each run's final test PSNR, SSIM, Gaussians and seconds, each run's PSNR-against-training-
time curve, and the time to quality: the training seconds each run needs to reach the lower of
simple_trainer default's and eg-train's final PSNRs.

Training seconds, the clock each trainer stops while it evaluates:
- eg-train: ``metrics.json`` ``history`` (the training clock at each evaluation), read once with
  the bench's ``read_json``;
- simple_trainer has no such clock. At each step of ``--save_steps`` it writes
  ``stats/train_stepK_rank0.json`` with ``ellipse_time`` (wall seconds since its loop began), then
  its checkpoint, then (the same step is in ``--eval_steps``) it evaluates and writes
  ``stats/val_stepK.json``. The seconds between those two files' modification times are the
  save and the evaluation of step K, which are not training; they are taken out of every later
  ``ellipse_time``. So the run passes the same steps to --save_steps and --eval_steps.
"""

from __future__ import annotations

import glob
import json
import os
import re
import sys
from pathlib import Path
from typing import Any

from exploregs_plugin.bench.runner import read_json
from exploregs_plugin.bench.time_quality import seconds_to_reach
from exploregs_plugin.engine.training_loop import METRICS_NAME


def simple_trainer_history(run_dir: str) -> list[dict[str, Any]]:
    """simple_trainer's evaluations as eg-train's ``history`` points (step counted from 1, as
    eg-train counts them: simple_trainer names step K-1's files after K-1): the step, the training
    seconds before it (its evaluations and saves taken out, see above), PSNR, SSIM, Gaussians.
    A step with an evaluation but no train stats (or the reverse) is left out."""
    stats = os.path.join(run_dir, "stats")
    trains = {}
    for path in glob.glob(os.path.join(stats, "train_step*_rank0.json")):
        match = re.fullmatch(r"train_step(\d+)_rank0\.json", os.path.basename(path))
        if match:
            trains[int(match.group(1))] = path
    points, not_training = [], 0.0
    for step in sorted(trains):
        val_path = os.path.join(stats, f"val_step{step:04d}.json")
        if not os.path.exists(val_path):
            continue
        with open(trains[step]) as f:
            train = json.load(f)
        with open(val_path) as f:
            val = json.load(f)
        points.append({"step": step + 1, "train_seconds": float(train["ellipse_time"]) - not_training,
                       "psnr": float(val["psnr"]), "ssim": float(val["ssim"]), "num_gaussians": int(val["num_GS"])})
        not_training += max(0.0, os.path.getmtime(val_path) - os.path.getmtime(trains[step]))
    return points


def seconds_by_interpolation(history: list[dict[str, Any]], level: float) -> float | None:
    """Training seconds at which the PSNR curve first reaches ``level``, linear between the two
    evaluations around the crossing (the first evaluation's seconds when it already reaches it);
    None when no evaluation does. A point estimate beside :func:`seconds_to_reach`'s upper bound."""
    previous = None
    for point in sorted(history, key=lambda p: p["step"]):
        if point["psnr"] >= level:
            if previous is None or point["psnr"] <= previous["psnr"]:
                return float(point["train_seconds"])
            fraction = (level - previous["psnr"]) / (point["psnr"] - previous["psnr"])
            return float(previous["train_seconds"] + fraction * (point["train_seconds"] - previous["train_seconds"]))
        previous = point
    return None


def time_of(work: str, name: str) -> str:
    """A part's wall seconds ("12.3 s"), or why there are none."""
    try:
        with open(os.path.join(work, "times", name)) as f:
            text = f.read().strip()
    except OSError:
        return "not run"
    return f"{text} s" if text.replace(".", "", 1).isdigit() else text


def curve_line(history: list[dict[str, Any]]) -> str:
    return ", ".join(f"{p['step']}: {p['psnr']:.2f} dB @ {p['train_seconds']:.1f} s" for p in history)


def main(work: str, out: str, steps: int, parts: list[str], c_args: str, c2_args: str) -> None:
    print(f"======== summary ({steps} steps for (b) and (c); parts run: {' '.join(parts)})")
    print(f"(a) bench.train_step ({time_of(work, 'a')}; train / gsplat is the ratio with the 1.15x target):")
    try:
        with open(os.path.join(out, "a_train_step.log")) as f:
            for line in f:
                if line.startswith(("# torch", "| ")):
                    print("   ", line.rstrip())
    except OSError:
        pass
    curves: dict[str, list[dict[str, Any]]] = {}
    for name in ("default", "seedsplit"):
        run = os.path.join(work, f"st-{name}")
        history = simple_trainer_history(run)
        trains = sorted(glob.glob(f"{run}/stats/train_step*_rank0.json"))
        if not history or not trains:
            print(f"(b) simple_trainer {name}: no stats ({time_of(work, 'b_' + name)})")
            continue
        with open(trains[-1]) as f:
            train = json.load(f)
        last = history[-1]
        curves[f"simple_trainer {name}"] = history
        print(f"(b) simple_trainer {name}: test PSNR {last['psnr']:.3f} dB, SSIM {last['ssim']:.4f}, "
              f"{last['num_gaussians']:,} Gaussians, training {last['train_seconds']:.1f} s (its loop's clock to step "
              f"{last['step']}, its saves and evaluations taken out), process wall {time_of(work, 'b_' + name)}, "
              f"peak {train['mem']:.2f} GiB (LPIPS not reported: random AlexNet)")
    for part, folder, args in (("c", "eg-train", c_args), ("c2", "eg-train-2", c2_args)):
        r = read_json(Path(work) / folder / METRICS_NAME)  # None: the run did not finish
        if r is None:
            print(f"({part}) eg-train {args}: no {METRICS_NAME} ({time_of(work, 'c_' + folder)})")
            continue
        curves[f"eg-train {args}"] = list(r.get("history", []))
        print(f"({part}) eg-train {args}: test PSNR {r['psnr']:.3f} dB, SSIM {r['ssim']:.4f}, "
              f"{r['num_gaussians']:,} Gaussians, train_seconds {r['train_seconds']:.1f} s (steps only), "
              f"wall_seconds {r['wall_seconds']:.1f} s, process wall {time_of(work, 'c_' + folder)}")
    print("curves (step: test PSNR @ training seconds):")
    for name, history in curves.items():
        print(f"    {name}: {curve_line(history)}")
    reference, ours = curves.get("simple_trainer default"), curves.get(f"eg-train {c_args}")
    if reference and ours:
        level = min(reference[-1]["psnr"], ours[-1]["psnr"])
        print(f"time to {level:.3f} dB (the lower final PSNR of simple_trainer default and eg-train {c_args}): "
              "first evaluation that reaches it (upper bound) / linear between evaluations")
        for name, history in curves.items():
            bound, point = seconds_to_reach(history, level), seconds_by_interpolation(history, level)
            text = "not reached" if bound is None else f"{bound:.1f} s / {point:.1f} s"
            print(f"    {name}: {text}")
    try:
        with open(os.path.join(out, "d_pytest_cuda.log")) as f:
            lines = f.read().splitlines()
        outcome = [ln for ln in lines if " in " in ln and any(w in ln for w in ("passed", "failed", "error", "skipped"))]
    except OSError:
        outcome = []
    print("(d) pytest -m cuda:", time_of(work, "d"), "|", outcome[-1].strip("= ") if outcome else "no outcome line")


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2], int(sys.argv[3]), sys.argv[4].split(), sys.argv[5], sys.argv[6])
