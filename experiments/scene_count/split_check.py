"""Replay the count rule of ``cap_max validated`` on the paired cut study's per-view scores.

    python experiments/scene_count/split_check.py outputs/cut-study/*-per-view.json [--k 5 8] [--tolerance 0.1]

Each JSON comes from ``cut_study.py RUN --per-view FILE``: every candidate count's PSNR on each of
the run's test views (never trained on). For every way of choosing k of those views for the rule
(the held-out views of a run), the rest are the test: the rule picks a count on the k views, and
the test views say what that pick cost, the best candidate's mean test PSNR less the pick's. Two
rules are compared: the plain one (the fewest Gaussians whose mean PSNR is within the tolerance of
the best) and the built one (``count_rule.pick_count``: per view, the mean deficit plus its
standard error). Printed per scene and k: the share of splits whose pick cost at most the
tolerance on the test views, the mean cost, and how often each count was picked.
"""

from __future__ import annotations

import argparse
import itertools
import json
from pathlib import Path

from exploregs_plugin.strategies.count_rule import pick_count


def pick_by_mean(counts: list[int], per_view: list[list[float]], tolerance: float) -> int:
    """The fewest Gaussians whose mean PSNR is within ``tolerance`` of the best mean."""
    means = [sum(p) / len(p) for p in per_view]
    best = max(means)
    return min((i for i in range(len(counts)) if means[i] >= best - tolerance), key=lambda i: counts[i])


def replay(counts: list[int], per_view: list[list[float]], k: int, tolerance: float, rule) -> dict:
    """Every split of the views into k for the rule and the rest for the test."""
    n = len(per_view[0])
    costs, picks = [], {}
    for chosen in itertools.combinations(range(n), k):
        rest = [v for v in range(n) if v not in chosen]
        i = rule(counts, [[p[v] for v in chosen] for p in per_view], tolerance)
        test = [sum(p[v] for v in rest) / len(rest) for p in per_view]
        costs.append(max(test) - test[i])
        picks[counts[i]] = picks.get(counts[i], 0) + 1
    return {"splits": len(costs), "within": sum(c <= tolerance + 1e-12 for c in costs) / len(costs),
            "mean_cost": sum(costs) / len(costs), "picks": dict(sorted(picks.items(), reverse=True))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("files", type=Path, nargs="+")
    ap.add_argument("--k", type=int, nargs="+", default=[5, 8])
    ap.add_argument("--tolerance", type=float, default=0.1)
    a = ap.parse_args()
    print(f"| scene | views | k | rule | pick costs <= {a.tolerance:g} dB | mean cost dB | picks (count: splits) |")
    print("|---|---|---|---|---|---|---|")
    for path in a.files:
        study = json.loads(path.read_text())
        counts = [r["gaussians"] for r in study["rows"]]
        per_view = [r["per_view"] for r in study["rows"]]
        scene = path.name.split("-")[0]
        n = len(per_view[0])
        for k in a.k:
            if not 1 <= k < n:
                continue
            for name, rule in (("mean", pick_by_mean), ("paired + se", pick_count)):
                r = replay(counts, per_view, k, a.tolerance, rule)
                picks = ", ".join(f"{c:,}: {m}" for c, m in r["picks"].items())
                print(f"| {scene} | {n} | {k} | {name} | {100 * r['within']:.0f}% of {r['splits']} | "
                      f"{r['mean_cost']:.3f} | {picks} |")


if __name__ == "__main__":
    main()
