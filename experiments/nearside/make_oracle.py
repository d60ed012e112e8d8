"""Build the "oracle points" scene: builtin:nearside whose SfM points gain one point per hidden
occluded pixel of the three clear training views (0009, 0017, 0023), at the ground-truth depth
and with the true colour. STRIDE 1 keeps every such pixel, 3 every third.

    python experiments/nearside/make_oracle.py "$OUT/scenes/nearside-oracle" 1
    python experiments/nearside/make_oracle.py "$OUT/scenes/nearside-oracle3" 3
"""

import argparse
import json
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from exploregs_plugin.analysis import nearside as ns
from scene_copy import copy_nearside, read_cameras, rewrite_sparse, sfm_points

CLEAR_TRAIN = ("0009.png", "0017.png", "0023.png")
OCCLUDED = 2  # the scene's mask label

parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("dst", type=Path, help="new scene folder (replaced if it exists)")
parser.add_argument("stride", type=int, nargs="?", default=1, help="keep every STRIDE-th hidden pixel")
args = parser.parse_args()

src, dst = copy_nearside(args.dst)
split = json.loads((src / "split.json").read_text())
rec, names, Ks_np, w2cs_np = read_cameras(src / "sparse" / "0")
Ks, w2cs = torch.tensor(Ks_np), torch.tensor(w2cs_np)
depth = {n: torch.tensor(np.load(src / "depths" / (n[:4] + ".npy")), dtype=torch.float64) for n in names}
train = [i for i, n in enumerate(names) if n in split["train"]]
train_depths = torch.stack([depth[names[i]] for i in train])

new_pts, new_rgb = [], []
for name in CLEAR_TRAIN:
    i = names.index(name)
    pts = ns.unproject(depth[name], Ks[i], w2cs[i]).reshape(-1, 3)
    seen = ns.seen_by(pts, w2cs[train], Ks[train], train_depths).sum(0)
    hidden = ns.hidden_from(pts, w2cs[train], Ks[train], train_depths).sum(0)
    label = torch.tensor(np.asarray(Image.open(src / "masks" / (name[:4] + ".png")))).reshape(-1)
    image = torch.tensor(np.asarray(Image.open(src / "images" / name)), dtype=torch.float64).reshape(-1, 3) / 255.0
    keep = torch.where((label == OCCLUDED) & (hidden > seen))[0][::args.stride]
    new_pts.append(pts[keep])
    new_rgb.append(image[keep])
new_pts, new_rgb = torch.cat(new_pts).numpy(), torch.cat(new_rgb).numpy()
points, rgb = sfm_points(rec)
rewrite_sparse(dst, rec, names, Ks_np, w2cs_np, np.concatenate([points, new_pts]), np.concatenate([rgb, new_rgb]))
print(f"{len(points)} SfM points + {len(new_pts)} interior points -> {dst}")
