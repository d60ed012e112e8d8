"""Does a paired cut, scored on views the run never trained on, choose the count that the test
views would choose? (Issue 55: the candidate rule after the held-out growth contrast failed.)

    python experiments/scene_count/cut_study.py RUN [--fractions 1 2 4 8] [--finetune-steps 1000]

RUN is a finished run trained with more test views than usual (e.g. ``--datamanager.test-every
6``). Its test views are split in two halves by position (even: validation, odd: test), neither
ever trained on. For each fraction f the run's final set is cut to N/f Gaussians (the most
significant, as ``eg-export --max-gaussians``) and fine-tuned F steps on the training views
(f = 1 is fine-tuned too, so that every candidate had the same steps since the snapshot: the
comparison is paired, from one snapshot). Each candidate is scored on both halves.

The rule: the smallest count whose validation PSNR is within ``--tolerance`` (0.1 dB) of the best
candidate's. Printed: each candidate's PSNR on each half, the count the rule picks on the
validation half, the count the same rule picks on the test half, and the test PSNR of the pick
against the best test PSNR. A rule that works picks on validation what the test half picks, or
a count whose test PSNR is within the tolerance of the best.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from exploregs_plugin.evaluation.metrics import evaluate
from exploregs_plugin.runs import load_run
from exploregs_plugin.runs.simplify import simplify


def halves(per_image: list[dict]) -> tuple[float, float]:
    """Mean PSNR over the even-positioned test views (validation) and the odd ones (test)."""
    even = [e["psnr"] for i, e in enumerate(per_image) if i % 2 == 0]
    odd = [e["psnr"] for i, e in enumerate(per_image) if i % 2 == 1]
    return sum(even) / len(even), sum(odd) / len(odd)


def pick(rows: list[dict], key: str, tolerance: float) -> dict:
    """The row of fewest Gaussians whose ``key`` PSNR is within ``tolerance`` of the best row's."""
    best = max(r[key] for r in rows)
    return min((r for r in rows if r[key] >= best - tolerance), key=lambda r: r["gaussians"])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run", type=Path)
    ap.add_argument("--fractions", type=int, nargs="+", default=[1, 2, 4, 8])
    ap.add_argument("--finetune-steps", type=int, default=1000)
    ap.add_argument("--tolerance", type=float, default=0.1)
    ap.add_argument("--per-view", type=Path, default=None,
                    help="also write each candidate's per-view PSNR of all the test views (in order) to this JSON")
    a = ap.parse_args()
    rows = []
    for fraction in a.fractions:
        run = load_run(a.run, "cpu")
        n = run.pipeline.model.num_gaussians
        start = time.perf_counter()
        done = simplify(run.pipeline, run.step, max(n // fraction, 1), a.finetune_steps)
        seconds = time.perf_counter() - start
        scored = evaluate(run.pipeline.model, run.pipeline.datamanager)
        validation, test = halves(scored["per_image"])
        rows.append({"fraction": fraction, "gaussians": done.after, "validation": validation, "test": test,
                     "per_view": [e["psnr"] for e in scored["per_image"]]})
        print(f"x1/{fraction}: {done.after} Gaussians, validation {validation:.3f} dB, test {test:.3f} dB "
              f"({len(scored['per_image'])} views; cut and {a.finetune_steps} steps in {seconds:.0f} s)", flush=True)
    if a.per_view is not None:
        a.per_view.write_text(json.dumps({"run": str(a.run), "finetune_steps": a.finetune_steps, "rows": rows}, indent=1))
    by_validation, by_test = pick(rows, "validation", a.tolerance), pick(rows, "test", a.tolerance)
    best_test = max(r["test"] for r in rows)
    print(f"\n{a.run}: candidates fine-tuned {a.finetune_steps} steps from the final snapshot, tolerance {a.tolerance} dB")
    print("| cut | Gaussians | validation PSNR | test PSNR |")
    print("|---|---:|---:|---:|")
    for r in rows:
        print(f"| x1/{r['fraction']} | {r['gaussians']} | {r['validation']:.3f} | {r['test']:.3f} |")
    print(f"rule on validation picks {by_validation['gaussians']} (x1/{by_validation['fraction']}); "
          f"on test it would pick {by_test['gaussians']} (x1/{by_test['fraction']}); "
          f"test PSNR of the validation pick {by_validation['test']:.3f} dB, best {best_test:.3f} dB "
          f"({by_validation['test'] - best_test:+.3f} dB)")


if __name__ == "__main__":
    main()
