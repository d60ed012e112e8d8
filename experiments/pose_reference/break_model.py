"""Do the checks flag a real model broken on purpose? A posed dataset's model with one run of
cameras (a quarter, in name order) mirrored (turned 180 degrees about its own down axis: it looks
away) or misplaced (moved to twice its distance from the points' centre), checked as eg-process
checks its own models, against the dataset's database.

    python experiments/pose_reference/break_model.py outputs/process/bonsai252-idle
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pycolmap

from exploregs_plugin.data.process import checks


def broken(rec: pycolmap.Reconstruction, names: list[str], how: str) -> pycolmap.Reconstruction:
    """A copy of ``rec`` with the cameras ``names`` posed wrong on purpose (``how``)."""
    out = pycolmap.Reconstruction(rec)
    centre = np.median([p.xyz for p in out.points3D.values()], axis=0)
    for im in out.images.values():
        if im.name not in names:
            continue
        R, t = im.cam_from_world().rotation.matrix(), im.cam_from_world().translation
        c = -R.T @ t
        R = np.diag([-1.0, 1.0, -1.0]) @ R if how == "mirrored" else R
        c = c + 2.0 * (c - centre) if how == "misplaced" else c
        out.frame(im.frame_id).rig_from_world = pycolmap.Rigid3d(pycolmap.Rotation3d(R), -R @ c)
    return out


def main(dataset: Path) -> None:
    rec = pycolmap.Reconstruction(str(dataset / "sparse" / "0"))
    names = sorted(im.name for im in rec.images.values() if im.has_pose)
    quarter = names[len(names) // 2: len(names) // 2 + len(names) // 4]
    print("| model | suspect | of them broken | looks away | jumps | disagree (warning) | passed |")
    print("|---|---|---|---|---|---|---|")
    for how in ("as posed", "mirrored", "misplaced"):
        model = rec if how == "as posed" else broken(rec, quarter, how)
        found = checks.check_model(model, names, dataset / "database.db")
        hit = len(set(found.suspect) & set(quarter)) if how != "as posed" else 0
        label = how if how == "as posed" else f"{how} ({len(quarter)} of {len(names)})"
        print(f"| {label} | {len(found.suspect)} | {hit} | "
              f"{len(found.looks_away)} | {len(found.jumps)} | {len(found.disagrees)} | {found.passed} |")


if __name__ == "__main__":
    main(Path(sys.argv[1]))
