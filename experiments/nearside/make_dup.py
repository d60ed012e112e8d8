"""Build the "clear views x4" scene: builtin:nearside with each clear training view (one that
faces the cabinet's opening: 0009, 0017, 0023) repeated COPIES more times in the training split.
The copies are named 1009, 2009, ... (image, depth, mask and camera identical to the original).

    python experiments/nearside/make_dup.py 3 "$OUT/scenes/nearside-clear4x"
"""

import argparse
import json
import shutil
from pathlib import Path

import numpy as np

from exploregs_plugin.data.builtin.layouts import view_kinds
from scene_copy import copy_nearside, read_cameras, rewrite_sparse, sfm_points

parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("copies", type=int, help="extra copies of each clear training view (3: four times in all)")
parser.add_argument("dst", type=Path, help="new scene folder (replaced if it exists)")
args = parser.parse_args()

src, dst = copy_nearside(args.dst)
preset = json.loads((src / "scene.json").read_text())["preset"]
split = json.loads((src / "split.json").read_text())
kinds = view_kinds(preset["n_views"], preset["test_every"])
clear_train = [f"{i:04d}.png" for i, clear in enumerate(kinds) if clear and f"{i:04d}.png" in split["train"]]
print("clear training views:", clear_train)

rec, names, Ks, w2cs = read_cameras(src / "sparse" / "0")
out_names, out_Ks, out_w2cs = [], [], []
for name, K, w2c in zip(names, Ks, w2cs):
    out_names.append(name)
    out_Ks.append(K)
    out_w2cs.append(w2c)
    if name not in clear_train:
        continue
    for c in range(args.copies):  # each copy right after its original, as in the measured runs
        stem = f"{1000 * (c + 1) + int(name[:4]):04d}"
        for sub, ext in (("images", ".png"), ("depths", ".npy"), ("masks", ".png")):
            shutil.copy(dst / sub / (name[:4] + ext), dst / sub / (stem + ext))
        out_names.append(stem + ".png")
        out_Ks.append(K)
        out_w2cs.append(w2c)
        split["train"].append(stem + ".png")
points, rgb = sfm_points(rec)
rewrite_sparse(dst, rec, out_names, np.stack(out_Ks), np.stack(out_w2cs), points, rgb)
(dst / "split.json").write_text(json.dumps(split, indent=1))
print(len(split["train"]), "training views,", len(split["test"]), "test views ->", dst)
