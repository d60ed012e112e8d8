"""Bytes of training state per Gaussian, counted from a real pipeline's tensors.

    python -m exploregs_plugin.bench.components.memory --methods exploregs-default exploregs-seedsplit exploregs-mcmc

Trains a few steps of each method on ``--data`` (so the optimizer moments and the strategy's
statistics exist), then sums ``nbytes`` over the parameters, their gradients (one float per
parameter float during a step), Adam's two moments and the strategy's per-Gaussian statistics,
and divides by the Gaussian count. The table also says how many Gaussians that persistent state
lets fit into 24, 80 and 140 GB; rendering needs room beside it (per-Gaussian projection
buffers and per-pair tile buffers), so the last columns keep ``--render-share`` of the memory
for it.
"""

from __future__ import annotations

import argparse
from dataclasses import replace

import torch

from exploregs_plugin.method_configs import get_method

MEMORIES_GB = (24, 80, 140)


def _nbytes(value: object) -> int:
    if isinstance(value, torch.Tensor):
        return value.numel() * value.element_size()
    if isinstance(value, dict):
        return sum(_nbytes(v) for v in value.values())
    if isinstance(value, (list, tuple)):
        return sum(_nbytes(v) for v in value)
    return 0


def bytes_per_gaussian(method: str, data: str, sh_degree: int, steps: int) -> dict[str, float]:
    """Per-Gaussian bytes of each part of the training state after ``steps`` steps."""
    config = replace(get_method(method).config, data=data, max_steps=max(steps, 100))
    config.pipeline.model = replace(config.pipeline.model, sh_degree=sh_degree)
    pipeline = config.pipeline.setup(config.schedule.resolve(config.max_steps), 0)
    for step in range(steps):
        pipeline.train_step(step)
    n = pipeline.model.num_gaussians
    params = sum(_nbytes(p) for p in pipeline.params.values())
    adam = sum(_nbytes(state) for opt in pipeline.optimizers.values() for state in opt.state.values())
    stats = _nbytes(pipeline.strategy_state.get("stats", {}))
    return {"gaussians": n, "params": params / n, "grads": params / n, "adam": adam / n, "stats": stats / n,
            "total": (2 * params + adam + stats) / n}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--methods", nargs="+", default=["exploregs-default", "exploregs-seedsplit", "exploregs-mcmc",
                                                         "exploregs-guided-occlusion"])
    parser.add_argument("--data", default="builtin:tiny")
    parser.add_argument("--sh-degree", type=int, default=3)
    parser.add_argument("--steps", type=int, default=60)
    parser.add_argument("--render-share", type=float, default=0.3,
                        help="fraction of the memory kept for rendering in the last columns")
    args = parser.parse_args(argv)
    fits = " | ".join(f"fit {g} GB" for g in MEMORIES_GB)
    print(f"SH degree {args.sh_degree}; bytes per Gaussian; 'fit' = persistent state only, "
          f"'fit*' = with {args.render_share:.0%} of the memory kept for rendering")
    print(f"| method | params | grads | Adam | strategy stats | total | {fits} | "
          + " | ".join(f"fit* {g} GB" for g in MEMORIES_GB) + " |")
    print("|---|" + "---|" * (5 + 2 * len(MEMORIES_GB)))
    for method in args.methods:
        row = bytes_per_gaussian(method, args.data, args.sh_degree, args.steps)
        full = [g * 1e9 / row["total"] / 1e6 for g in MEMORIES_GB]
        kept = [f * (1.0 - args.render_share) for f in full]
        print(f"| {method} | {row['params']:.0f} | {row['grads']:.0f} | {row['adam']:.0f} | {row['stats']:.0f} | "
              f"{row['total']:.0f} | " + " | ".join(f"{f:.1f}M" for f in full) + " | "
              + " | ".join(f"{f:.1f}M" for f in kept) + " |")


if __name__ == "__main__":
    main()
