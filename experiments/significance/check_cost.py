"""What the end-of-run cut's check costs: Pipeline._final_cut on a run's checkpoint, timed with the
check off (final_cut_tolerance 0) and on, twice each in turn, on one thread.

    python experiments/significance/check_cost.py RUN_DIR/checkpoints/step-0001000.pt
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import time

import torch

from exploregs_plugin.runs.load import load_run


def main(checkpoint: str, tolerance: float) -> None:
    torch.set_num_threads(1)
    pipeline = load_run(checkpoint, "cpu").pipeline
    saved, strategy = copy.deepcopy(pipeline.state_dict()), pipeline.strategy
    last = pipeline.schedule.max_steps - 1
    for tol in (0.0, tolerance, 0.0, tolerance):
        pipeline.load_state_dict(copy.deepcopy(saved))
        pipeline.strategy = dataclasses.replace(strategy, final_cut_tolerance=tol)
        start = time.perf_counter()
        _, lines = pipeline._final_cut(last)
        print(f"tolerance {tol:g}: {time.perf_counter() - start:.2f} s; {lines[0] if lines else ''}", flush=True)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoint", help="a checkpoint file (or a run folder: its latest)")
    parser.add_argument("--tolerance", type=float, default=0.1)
    args = parser.parse_args()
    main(args.checkpoint, args.tolerance)
