"""eg-train: train a method on a dataset.

    eg-train exploregs-seedsplit --data PATH        # train
    eg-train --resume RUN_DIR [--device DEVICE]     # continue an interrupted run
"""

from __future__ import annotations

import sys

import tyro

from exploregs_plugin.analysis.tensorboard import BranchGradientLogger
from exploregs_plugin.scripts import run_cli
from exploregs_plugin.method_configs import MethodRegistryError, all_methods
from exploregs_plugin.pipeline import NonFiniteError
from exploregs_plugin.trainer import Trainer, TrainerConfig


def _fail(message: str, code: int) -> "SystemExit":
    print(f"eg-train: error: {message}", file=sys.stderr)
    return SystemExit(code)


def parse_config(argv: list[str]) -> TrainerConfig:
    """Turn the command line into a TrainerConfig (one tyro subcommand per method)."""
    try:
        methods = all_methods()
    except MethodRegistryError as err:
        raise _fail(str(err), 2) from err
    if argv and not argv[0].startswith("-") and argv[0] not in methods:
        raise _fail(f"unknown method {argv[0]!r}; known methods: {', '.join(sorted(methods))}", 2)
    subcommands = tyro.extras.subcommand_type_from_defaults(
        {name: spec.config for name, spec in methods.items()},
        {name: spec.description for name, spec in methods.items()},
    )
    return tyro.cli(subcommands, args=argv, description="Train a 3D Gaussian Splatting scene with ExploreGS.")


def main(argv: list[str]) -> dict:
    if argv[:1] == ["--resume"]:
        if len(argv) not in (2, 4) or (len(argv) == 4 and argv[2] != "--device"):
            raise _fail("usage: eg-train --resume RUN_DIR [--device auto|cpu|cuda|cuda:N]", 2)
        device = argv[3] if len(argv) == 4 else None
        trainer = Trainer.from_run(argv[1], callbacks=[BranchGradientLogger()], device=device)
    else:
        trainer = parse_config(argv).setup(callbacks=[BranchGradientLogger()])
    print(f"run folder: {trainer.run_dir}", file=sys.stderr)
    try:
        metrics = trainer.train()
    except KeyboardInterrupt:
        raise _fail(f"interrupted; resume with: eg-train --resume {trainer.run_dir}", 130)
    except NonFiniteError as err:
        raise _fail(str(err), 1) from err
    print(f"done: test PSNR {metrics['psnr']:.2f} dB, SSIM {metrics['ssim']:.4f}, "
          f"{metrics['num_gaussians']} Gaussians, {metrics['train_seconds']:.1f} s; "
          f"metrics in {trainer.run_dir / 'metrics.json'}", file=sys.stderr)
    return metrics


def entrypoint() -> None:
    run_cli("eg-train", main, sys.argv[1:])


if __name__ == "__main__":
    entrypoint()
