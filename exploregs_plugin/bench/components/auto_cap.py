"""Where MCMC's ``cap_max auto`` stops growth, replayed on one traced run.

    python -m exploregs_plugin.bench.components.auto_cap trace OUT.json --stop-step 6000 -- \\
        exploregs-mcmc --data ../shared/scenes/beer --data-factor 6 --max-steps 30000 --strategy.cap-max 60000
    python -m exploregs_plugin.bench.components.auto_cap replay OUT.json [--min-drop 0.01 0.02 ...] [--span 1 5 10]

``trace`` trains a run with a fixed (large) cap and records, for every step, its training view,
its data loss (the loss the automatic cap reads) and the Gaussian count, until ``--stop-step``.
``replay`` feeds that trace to the automatic cap's rule (:func:`~exploregs_plugin.strategies.
mcmc.auto_close_window`, the code a run uses) for each pair of constants and prints the step and count at
which it would stop growth. Until that refinement an automatic run and the traced run are the
same run (same seed, same draws, same bits), so the stop it prints is the one an automatic run
of that schedule makes; a stop the trace does not reach is printed as "beyond".
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from dataclasses import replace
from pathlib import Path
from typing import Any

from exploregs_plugin.callbacks import TrainingCallback


class _TraceDone(Exception):
    """Raised by the recorder before the stop step: the trace is complete."""


class _Recorder(TrainingCallback):
    """Records (step, view, data loss, count) after every step and ends the run at ``stop_step``."""

    def __init__(self, stop_step: int) -> None:
        self.stop_step = stop_step
        self.rows: list[tuple[int, int, float, int]] = []
        self.refinements: list[tuple[int, dict[str, int]]] = []

    def before_step(self, trainer: Any, step: int) -> None:
        if step >= self.stop_step:
            raise _TraceDone

    def after_step(self, trainer: Any, step: int, stats: dict[str, Any]) -> None:
        terms = stats["terms"]
        loss = stats["loss"] - terms["reg"] if "reg" in terms else stats["loss"]
        view = stats["views"][0]
        self.rows.append((step - 1, int(view), float(loss), int(trainer.pipeline.model.num_gaussians)))
        counts = {k: int(v) for k, v in stats["counts"].items() if k != "perturbed" and int(v)}
        if counts:  # what the refinement did: relocated (dead rows moved), added, explored
            self.refinements.append((step - 1, counts))


def trace(out: Path, stop_step: int, train_args: list[str]) -> dict[str, Any]:
    """Train ``train_args`` (an eg-train command line: METHOD then its flags) to ``stop_step`` and
    write the trace."""
    from exploregs_plugin.bench.spec import parse_overrides
    from exploregs_plugin.method_configs import get_method
    from exploregs_plugin.engine.trainer import Trainer

    method, *args = train_args
    config = parse_overrides(get_method(method).config, args, "the traced command")
    run_dir = out.with_suffix("")
    config = replace(config, run_dir=run_dir, quiet=True, tensorboard=False, save_eval_images=False,
                     eval_count=0, checkpoint_every=10**9)
    recorder = _Recorder(stop_step)
    trainer = Trainer(config, callbacks=[recorder])
    try:
        trainer.train()
    except _TraceDone:
        pass
    filled = trainer.pipeline.strategy  # the schedule's refinement steps filled in
    result = {"command": train_args, "stop_step": stop_step, "cap_max": filled.cap_max,
              "refine_start_iter": filled.refine_start_iter, "refine_stop_iter": filled.refine_stop_iter,
              "refine_every": filled.refine_every, "num_train_views": len(trainer.pipeline.datamanager.train_cameras),
              "rows": recorder.rows, "refinements": recorder.refinements}
    tmp = out.with_suffix(".tmp")
    tmp.write_text(json.dumps(result))
    os.replace(tmp, out)
    return result


def replay(trace_data: dict[str, Any], min_drop: float, span: int, patience: int) -> tuple[int | None, int | None]:
    """(step, count) at which the automatic cap with these constants stops growth on the trace,
    or (None, None) when it does not stop within it."""
    from exploregs_plugin.strategies.mcmc import NO_CAP, auto_add_loss, auto_close_window, auto_state

    state = auto_state()
    start, stop, every = trace_data["refine_start_iter"], trace_data["refine_stop_iter"], trace_data["refine_every"]
    before = trace_data["rows"][0][3]  # the count after the previous step: the rows are every step in order
    for step, _view, loss, count in trace_data["rows"]:
        if step >= stop:
            break
        auto_add_loss(state, loss)
        if start < step and step % every == 0:
            if auto_close_window(state, before, min_drop, span, patience) != NO_CAP:
                return step, before  # the traced run grew at this step; an automatic one stops here
        before = count
    return None, None


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    t = sub.add_parser("trace", help="train with a fixed cap and record the loss of every step")
    t.add_argument("out", type=Path)
    t.add_argument("--stop-step", type=int, required=True)
    r = sub.add_parser("replay", help="where the automatic cap would stop on a trace")
    r.add_argument("traces", type=Path, nargs="+")
    r.add_argument("--min-drop", type=float, nargs="+", default=[0.005, 0.01, 0.02, 0.05])
    r.add_argument("--span", type=int, nargs="+", default=[1, 5, 10])
    r.add_argument("--patience", type=int, nargs="+", default=[2])
    if "--" in argv:
        cut = argv.index("--")
        args, train_args = parser.parse_args(argv[:cut]), argv[cut + 1:]
    else:
        args, train_args = parser.parse_args(argv), []
    if args.command == "trace":
        if not train_args:
            parser.error("trace needs an eg-train command line after --")
        result = trace(args.out, args.stop_step, train_args)
        print(f"{args.out}: {len(result['rows'])} steps")
        return
    print("| trace | span | min drop | patience | stop step | count |")
    print("|---|---|---|---|---|---|")
    for path in args.traces:
        data = json.loads(path.read_text())
        for span in args.span:
            for drop in args.min_drop:
                for patience in args.patience:
                    step, count = replay(data, drop, span, patience)
                    where = ("beyond", f"> {data['rows'][-1][3]}") if step is None else (str(step), str(count))
                    print(f"| {path.stem} | {span} | {drop:g} | {patience} | {where[0]} | {where[1]} |")


if __name__ == "__main__":
    main()
