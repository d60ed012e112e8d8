"""One bench run in its own process: ``python -m exploregs_plugin.bench.worker RUN_DIR [--resume]``.

Trains the config in ``RUN_DIR/bench_job.yml`` (or resumes the run folder from its newest
checkpoint). Any failure is written to ``RUN_DIR/error.txt`` (one line) and the traceback to
stderr, and the exit code is 1, so the bench records it and carries on.
"""

from __future__ import annotations

import sys
import traceback
from pathlib import Path

from exploregs_plugin.bench.files import ERROR_NAME, JOB_NAME


def train(run_dir: Path, resume: bool) -> dict:
    from exploregs_plugin.analysis.tensorboard import BranchGradientLogger
    from exploregs_plugin.io.config_files import load_config
    from exploregs_plugin.engine.trainer import Trainer

    callbacks = [BranchGradientLogger()]
    if resume:
        trainer = Trainer.from_run(run_dir, quiet=True, callbacks=callbacks)
    else:
        config = load_config(run_dir / JOB_NAME)
        trainer = Trainer(config, run_dir=run_dir, callbacks=callbacks)
    return trainer.train()


def main(argv: list[str]) -> int:
    if not argv or len(argv) > 2 or (len(argv) == 2 and argv[1] != "--resume"):
        print("usage: python -m exploregs_plugin.bench.worker RUN_DIR [--resume]", file=sys.stderr)
        return 2
    run_dir = Path(argv[0])
    try:
        metrics = train(run_dir, resume=len(argv) == 2)
    except BaseException as err:  # the bench needs every failure, Ctrl-C included, in one line
        message = f"{type(err).__name__}: {err}".strip().replace("\n", " ")
        (run_dir / ERROR_NAME).write_text(message + "\n")
        traceback.print_exc()
        return 130 if isinstance(err, KeyboardInterrupt) else 1
    print(f"done: PSNR {metrics['psnr']:.3f} dB, {metrics['num_gaussians']} Gaussians, "
          f"{metrics['train_seconds']:.1f} s", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
