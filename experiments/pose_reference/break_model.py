"""Do the checks flag a real model broken on purpose? A posed dataset's model with one run of
cameras (a quarter, in name order) mirrored (turned 180 degrees about its own down axis: it looks
away) or misplaced (moved to twice its distance from the points' centre), checked as eg-process
checks its own models, against the dataset's database.

    python experiments/pose_reference/break_model.py outputs/process/bonsai252-idle
"""

from __future__ import annotations

import sys
from pathlib import Path

import pycolmap

from exploregs_plugin.bench.components.pose_agreement import break_cameras
from exploregs_plugin.data.process import checks


def main(dataset: Path) -> None:
    rec = pycolmap.Reconstruction(str(dataset / "sparse" / "0"))
    names = sorted(im.name for im in rec.images.values() if im.has_pose)
    quarter = names[len(names) // 2: len(names) // 2 + len(names) // 4]
    print("| model | suspect | of them broken | looks away | jumps | seams | disagree (warning) | passed |")
    print("|---|---|---|---|---|---|---|---|")
    for how in ("as posed", "mirrored", "misplaced"):
        model = rec if how == "as posed" else break_cameras(rec, quarter, how)
        found = checks.check_model(model, names, dataset / "database.db")
        hit = len(set(found.suspect) & set(quarter)) if how != "as posed" else 0
        label = how if how == "as posed" else f"{how} ({len(quarter)} of {len(names)})"
        print(f"| {label} | {len(found.suspect)} | {hit} | "
              f"{len(found.looks_away)} | {len(found.jumps)} | {len(found.seams)} | {len(found.disagrees)} | {found.passed} |")


if __name__ == "__main__":
    main(Path(sys.argv[1]))
