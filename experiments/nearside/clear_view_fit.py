"""PSNR of a run on the hidden occluded pixels of the clear views: the three clear training views
(0009, 0017, 0023, with their repeats in the clear-views-x4 scene) and the clear test view 0008,
beside the other-region pixels of the same views. "Hidden" is judged against the scene's 28
original training views (repeats named 1009, 2009, ... are left out). One line per run.

    python experiments/nearside/clear_view_fit.py "$OUT"/runs/default/seed{0,1,2}
"""

import argparse

from exploregs_plugin.analysis import nearside as ns
from exploregs_plugin.analysis import nearside_report as nr
from exploregs_plugin.runs import load_run

CLEAR = {"train": ("0009.png", "0017.png", "0023.png"), "test": ("0008.png",)}
OTHER, OCCLUDED = 0, 2  # the scene's mask labels

parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("runs", nargs="+", help="run folders (or checkpoint files)")
args = parser.parse_args()

for run_dir in args.runs:
    pipeline = load_run(run_dir, "cpu").pipeline
    views = {split: nr.scene_views(pipeline.datamanager, split) for split in ("train", "test")}
    train = views["train"]
    original = [i for i, c in enumerate(train.cameras) if int(c.name[:4]) < 1000]
    V, K, D = train.viewmats[original], train.Ks[original], train.depths[original]
    parts = ["/".join(str(run_dir).rstrip("/").split("/")[-2:])]
    for split, vs in views.items():
        idx = [i for i, c in enumerate(vs.cameras) if c.name in CLEAR[split]]
        sub = nr.SceneViews([vs.cameras[i] for i in idx], vs.images[idx], vs.depths[idx], vs.labels[idx])
        sq = nr.squared_errors(pipeline, sub)
        hid_sum = hid_n = other_sum = other_n = 0
        for k, cam in enumerate(sub.cameras):
            pts = ns.unproject(sub.depths[k], cam.K.double(), cam.viewmat.double()).reshape(-1, 3)
            shape = sub.depths[k].shape
            seen = ns.seen_by(pts, V, K, D).sum(0).reshape(shape)
            hidden = ns.hidden_from(pts, V, K, D).sum(0).reshape(shape)
            m = (sub.labels[k] == OCCLUDED) & (hidden > seen)
            o = sub.labels[k] == OTHER
            hid_sum, hid_n = hid_sum + float(sq[k][m].sum()), hid_n + int(m.sum())
            other_sum, other_n = other_sum + float(sq[k][o].sum()), other_n + int(o.sum())
        parts.append(f"{split}-clear: hidden {ns.psnr_of(hid_sum, hid_n):.2f} ({hid_n} px) "
                     f"other {ns.psnr_of(other_sum, other_n):.2f}")
    print(" | ".join(parts))
