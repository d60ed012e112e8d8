"""The "other" and "far" rows beside the reference predictors: a run's PSNR on the test views'
other / far pixels, and that of predictors made from the truth (one colour for the region, 3x3,
5x5, 9x9 box blurs, the truth moved by one pixel). eg-analyze nearside gives the occluded rows
(nearside_references.csv).

    python experiments/nearside/references_other.py "$OUT/runs/default/seed0"
"""

import argparse

from exploregs_plugin.analysis import nearside as ns
from exploregs_plugin.analysis import nearside_report as nr
from exploregs_plugin.runs import load_run

parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("run", help="run folder (or checkpoint file)")
args = parser.parse_args()

pipeline = load_run(args.run, "cpu").pipeline
test = nr.scene_views(pipeline.datamanager, "test")
sq = nr.squared_errors(pipeline, test)
for label, name in ((0, "other"), (1, "far")):
    m = test.labels == label
    model = ns.psnr_of(float(sq[m].sum()), int(m.sum()))
    refs = {k: round(v, 2) for k, v in ns.reference_psnrs(test.images, m).items()}
    print(f"{name}: {int(m.sum())} px, model {model:.2f}, references {refs}")
