"""The two tables of docs/results.md's near-side section (baseline and tried entries; paired
differences to Default on the same seed), as Markdown on stdout.

Reads RUNS/<entry>/seed<k>/metrics.json (test PSNR; region PSNR pooled over the test views; the
occluded region of the clear test view 0008) and PIX/<entry>-seed<k>/nearside_references.csv
(hidden and out-of-view parts, from `eg-analyze nearside --checkpoints none --no-train-pixels`).
Defaults: RUNS = OUT/runs, PIX = OUT/analysis/pix, OUT = $OUT or outputs/experiments/nearside.
A mean over other than three seeds gives the count in brackets.

    python experiments/nearside/make_tables.py                      # "$OUT"
    python experiments/nearside/make_tables.py --runs DIR --pix DIR
"""

import argparse
import csv
import json
import os
import statistics as st
from pathlib import Path

LABELS = {  # entry folder -> row name in docs/results.md
    "default": "default", "seedsplit": "seedsplit", "occlusion": "occlusion", "guided": "guided",
    "guided-occlusion": "guided-occlusion", "em100": "error-mass densification",
    "em050": "error-mass, half the growth", "default-clear4x": "Default, clear views x4",
    "default-oracle3": "Default, oracle points 1/3", "default-oracle": "Default, oracle points",
}
KEYS = [("psnr", "PSNR"), ("occ", "occluded"), ("hid", "hidden part"), ("oov", "out-of-view part"),
        ("clear", "occluded, clear test view"), ("far", "far"), ("other", "other")]

parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("out", nargs="?", type=Path, default=Path(os.environ.get("OUT") or "outputs/experiments/nearside"))
parser.add_argument("--runs", type=Path, help="folder of <entry>/seed<k> runs (default OUT/runs)")
parser.add_argument("--pix", type=Path, help="folder of <entry>-seed<k> eg-analyze outputs (default OUT/analysis/pix)")
args = parser.parse_args()
RUNS = args.runs or args.out / "runs"
PIX = args.pix or args.out / "analysis" / "pix"


def load(entry: str, seed: int) -> dict | None:
    f = RUNS / entry / f"seed{seed}" / "metrics.json"
    if not f.exists():
        return None
    d = json.loads(f.read_text())
    clear = [e for e in d["per_image"] if e.get("name", "").startswith("0008")][0]
    row = {"psnr": d["psnr"], "occ": d["region_psnr"]["occluded"], "clear": clear["region_psnr"]["occluded"],
           "far": d["region_psnr"]["far"], "other": d["region_psnr"]["other"], "n": d["num_gaussians"]}
    ref = PIX / f"{entry}-seed{seed}" / "nearside_references.csv"
    if ref.exists() and entry != "default-clear4x":  # its repeated views change the hidden / out-of-view split
        with open(ref) as f:
            for r in csv.DictReader(f):
                if r["split"] == "test" and r["part"] != "occluded":
                    row["hid" if r["part"] == "occluded-hidden" else "oov"] = float(r["model"])
    return row


def fmt(vals: list, signed: bool = False) -> str:
    vals = [v for v in vals if v is not None]
    if not vals:
        return "n/a"
    s = f"{st.mean(vals):+.2f}" if signed else f"{st.mean(vals):.2f}"
    if len(vals) > 1:
        s += f" ± {st.stdev(vals):.2f}"
    return s + ("" if len(vals) == 3 else f" ({len(vals)})")


print("| entry | " + " | ".join(k[1] for k in KEYS) + " | Gaussians | seeds |")
print("|---|" + "---|" * (len(KEYS) + 2))
for e, label in LABELS.items():
    rows = {s: r for s in range(3) if (r := load(e, s))}
    if rows:
        cells = [fmt([r.get(k) for r in rows.values()]) for k, _ in KEYS]
        n = round(st.mean(r["n"] for r in rows.values()))
        print(f"| {label} | " + " | ".join(cells) + f" | {n:,} | {','.join(map(str, rows))} |")
print()
print("| entry | ΔPSNR | Δoccluded | Δhidden part | Δout-of-view part | Δclear view, occluded | ΔGaussians | seeds |")
print("|---|---|---|---|---|---|---|---|")
for e, label in list(LABELS.items())[1:]:
    pairs = [(a, b) for s in range(3) if (a := load(e, s)) and (b := load("default", s))]
    if not pairs:
        continue

    def d(k: str) -> str:
        return fmt([a[k] - b[k] if a.get(k) is not None and b.get(k) is not None else None for a, b in pairs], True)

    dn = round(st.mean(a["n"] - b["n"] for a, b in pairs))
    print(f"| {label} | {d('psnr')} | {d('occ')} | {d('hid')} | {d('oov')} | {d('clear')} | {dn:+,} | {len(pairs)} |")
