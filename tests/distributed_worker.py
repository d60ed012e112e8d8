"""Run under torchrun by tests/test_distributed.py (not a test module itself).

    torchrun --standalone --nproc-per-node 2 tests/distributed_worker.py OUT SPEC_JSON

SPEC_JSON is a list of {"name", "argv", "diverge_at"}: each entry is an eg-train command line,
trained in turn in one process group. Every rank saves its final parameters and Gaussian count
to OUT/NAME/rank{R}.pt. With "diverge_at": S, rank 1 nudges one opacity after step S, and the
error of the next checkpoint's cross-rank check is saved to OUT/NAME/rank{R}.error instead.
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import torch

from exploregs_plugin.runtime.distributed import DivergenceError, World, leave_world
from exploregs_plugin.scripts.train import parse_config


def run(out: Path, entry: dict) -> None:
    trainer = parse_config(entry["argv"]).setup()
    folder = out / entry["name"]
    folder.mkdir(parents=True, exist_ok=True)
    rank = trainer.world.rank
    diverge_at = entry.get("diverge_at")
    if diverge_at is not None and rank == 1:
        step_once = trainer.pipeline.train_step

        def nudged(step: int) -> dict:
            stats = step_once(step)
            if step == diverge_at:
                with torch.no_grad():
                    trainer.pipeline.params["opacities"][0] += 1e-4
            return stats

        trainer.pipeline.train_step = nudged
    try:
        trainer.train()
    except DivergenceError as err:
        (folder / f"rank{rank}.error").write_text(str(err))
        return
    params = {k: v.detach().clone() for k, v in trainer.pipeline.params.items()}
    torch.save({"params": params, "num_gaussians": trainer.pipeline.model.num_gaussians,
                "counts": trainer.op_totals}, folder / f"rank{rank}.pt")


def main() -> None:
    out = Path(sys.argv[1])
    entries = json.loads(sys.argv[2])
    try:
        for entry in entries:
            run(out, entry)
    finally:
        leave_world(World(int(os.environ["RANK"]), int(os.environ["WORLD_SIZE"])))

if __name__ == "__main__":
    main()
