"""Do the checks catch every wrong model the mapper makes? The test arc (24 views over a tiled
floor, tests/test_data_process.py) posed once per RANSAC seed of two-view verification: each
seed gives other inliers, and the global mapper another model. Prints, per seed, whether the kept
model passed its checks and how many cameras agree with the true ones (2 degrees, 2% of the
extent); a model that passed with fewer than 24 is a wrong model the checks missed.

    python experiments/pose_reference/seed_sweep.py OUT exhaustive 1 2 3
    python experiments/pose_reference/seed_sweep.py OUT retrieval 1 2 3
"""

from __future__ import annotations

import json
import shutil
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pycolmap

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tests"))
from test_data_process import CONFIG, N_VIEWS, render_capture  # noqa: E402

from exploregs_plugin.bench.components.pose_agreement import agreement, colmap_cameras  # noqa: E402
from exploregs_plugin.data.process import process_capture, sfm  # noqa: E402


def main(out: Path, matching: str, seeds: list[int]) -> None:
    photos = out / "photos"
    if not (photos / f"{N_VIEWS - 1:04d}.png").exists():
        _, c2ws = render_capture(photos)
        np.save(out / "true_c2ws.npy", c2ws)
    reference = dict(zip([f"{i:04d}.png" for i in range(N_VIEWS)], np.load(out / "true_c2ws.npy")))
    print("| matching | seed | remedied | passed | within |")
    print("|---|---|---|---|---|")
    for seed in seeds:
        def seeded(seed: int = seed) -> pycolmap.TwoViewGeometryOptions:
            options = pycolmap.TwoViewGeometryOptions()
            options.ransac.random_seed = seed
            return options

        sfm.verification_options = seeded
        dataset = out / f"{matching}-{seed}"
        shutil.rmtree(dataset, ignore_errors=True)
        report = process_capture([photos], dataset, replace(CONFIG, matching=matching, verbose=False))
        found = agreement(colmap_cameras(dataset), reference)
        state = json.loads((dataset / "process_state.json").read_text())["stages"]["mapping"]
        kept = f"{state['pairs_kept']}, {state['mapper']}" if len(state["attempts"]) > 1 else "no"
        print(f"| {matching} | {seed} | {kept} | {report['checks']['passed']} | "
              f"{found['within']} of {N_VIEWS} |", flush=True)


if __name__ == "__main__":
    main(Path(sys.argv[1]), sys.argv[2], [int(s) for s in sys.argv[3:]])
