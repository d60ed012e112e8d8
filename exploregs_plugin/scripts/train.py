"""eg-train: train a method on a dataset.

    eg-train exploregs-seedsplit --data PATH        # train
    eg-train --resume RUN_DIR [--device DEVICE]     # continue an interrupted run
"""

from __future__ import annotations

import contextlib
import io
import signal
import sys

import tyro

from exploregs_plugin.analysis.tensorboard import BranchGradientLogger
from exploregs_plugin.configs import tyro_error_text
from exploregs_plugin.scripts import run_cli
from exploregs_plugin.method_configs import MethodRegistryError, all_methods
from exploregs_plugin.pipeline import NonFiniteError
from exploregs_plugin.trainer import Stopped, Trainer, TrainerConfig


DESCRIPTION = ("Train a 3D Gaussian Splatting scene with ExploreGS. Continue an interrupted run with: "
               "eg-train --resume RUN_DIR [--device DEVICE].")


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
    captured = io.StringIO()
    try:
        with contextlib.redirect_stderr(captured):
            return tyro.cli(subcommands, args=argv, description=DESCRIPTION)
    except SystemExit as exit_:
        if exit_.code in (0, None):  # --help
            sys.stderr.write(captured.getvalue())
            raise
        raise _fail(tyro_error_text(captured.getvalue()) or f"invalid arguments {argv}", 2) from None


def _stop_before_training(signum: int, frame: object) -> None:
    raise Stopped(signum)


def main(argv: list[str]) -> dict:
    # Before the loop installs its own handler, SIGTERM ends the command with one line (pycolmap's
    # failure handler would otherwise print a crash dump); during training it checkpoints first.
    signal.signal(signal.SIGTERM, _stop_before_training)
    trainer = None
    try:
        if argv[:1] == ["--resume"]:
            if len(argv) not in (2, 4) or (len(argv) == 4 and argv[2] != "--device"):
                raise _fail("usage: eg-train --resume RUN_DIR [--device auto|cpu|cuda|cuda:N]", 2)
            device = argv[3] if len(argv) == 4 else None
            trainer = Trainer.from_run(argv[1], callbacks=[BranchGradientLogger()], device=device)
            print(f"resuming {trainer.run_dir} from step {trainer.start_step} ({trainer.last_checkpoint})",
                  file=sys.stderr)
        else:
            trainer = parse_config(argv).setup(callbacks=[BranchGradientLogger()])
        print(f"run folder: {trainer.run_dir}", file=sys.stderr)
        metrics = trainer.train()
    except Stopped as err:
        resume = f"; resume with: eg-train --resume {trainer.run_dir}" if err.checkpoint is not None else ""
        raise _fail(f"{err}{resume}", err.exit_code) from None
    except KeyboardInterrupt:
        where = f"; resume with: eg-train --resume {trainer.run_dir}" if trainer is not None else ""
        raise _fail(f"interrupted{where}", 130) from None
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
