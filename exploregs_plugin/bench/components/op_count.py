"""Torch operators per training step, by method: the glue a step pays for on a CPU (interpreter and
dispatcher time per operator) and on a GPU (a kernel launch per operator).

    python -m exploregs_plugin.bench.components.op_count
    python -m exploregs_plugin.bench.components.op_count --methods exploregs-default --top 15

Trains ``--warmup`` steps of ``--data`` (the built-in scene by default), then records ``--steps``
more with torch's profiler (CPU activity) and counts the *top-level* operators: each operator
event that no other operator encloses (``aten::mul`` called by the step, not the ``aten::empty``
inside it; a backward function's operators count, under the autograd node that runs them).
A compiled kernel called through its Python binding is not a torch operator and counts only by the
operators it calls itself. The window lies inside the densification window, between two
refinements (the 300-step schedule refines every 100 steps): it counts the step a growing run
makes 99 times in 100, whose count is the same at every step of the window (20 or 40 steps give
the same figure).

The count is deterministic for a seed, a scene and a renderer backend, so a test pins it
(tests/test_bench_op_count.py) and fails when a method's count grows by more than 10%.
"""

from __future__ import annotations

import argparse
import collections
from dataclasses import dataclass, replace

import torch

DEFAULT_METHODS = ("exploregs-default", "exploregs-seedsplit", "exploregs-mcmc")


@dataclass(frozen=True)
class OpCount:
    """Top-level operators of ``steps`` profiled training steps."""

    method: str
    backend: str
    steps: int
    by_name: dict[str, int]
    """Operator name -> calls over the profiled steps."""

    @property
    def per_step(self) -> float:
        return sum(self.by_name.values()) / max(self.steps, 1)


def _is_operator(name: str) -> bool:
    # aten, prim and registered custom ops carry a namespace; the profiler's own scopes
    # ("ProfilerStep#3", "autograd::engine::evaluate_function: ...", "Optimizer.step#Adam.step")
    # do not count as operators.
    return "::" in name and not name.startswith(("autograd::", "ProfilerStep", "Optimizer."))


def top_level_operators(events) -> collections.Counter:
    """Name -> count of the operator events that no other operator event encloses (torch.profiler
    FunctionEvents, with their ``cpu_parent`` links)."""
    counts: collections.Counter = collections.Counter()
    for event in events:
        if not _is_operator(event.name):
            continue
        parent = event.cpu_parent
        while parent is not None and not _is_operator(parent.name):
            parent = parent.cpu_parent
        if parent is None:
            counts[event.name] += 1
    return counts


def count_operators(method: str, data: str = "builtin:default", backend: str = "cpp", warmup: int = 20,
                    steps: int = 10, max_steps: int = 300, seed: int = 0, data_factor: int | None = None) -> OpCount:
    """Train ``warmup`` steps of ``method`` on one thread, then count the top-level operators of
    ``steps`` more (with the schedule of a ``max_steps``-step run)."""
    from torch.profiler import ProfilerActivity, profile

    from exploregs_plugin.method_configs import get_method

    base = get_method(method).config
    config = replace(base, data=data, data_factor=data_factor, max_steps=max_steps, device="cpu", seed=seed)
    config.pipeline.model.raster = replace(config.pipeline.model.raster, backend=backend)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        pipeline = config.pipeline.setup(config.schedule.resolve(max_steps), config.seed, torch.device("cpu"))
        for step in range(warmup):
            pipeline.train_step(step)
        with profile(activities=[ProfilerActivity.CPU]) as prof:
            for step in range(warmup, warmup + steps):
                pipeline.train_step(step)
    finally:
        torch.set_num_threads(threads)
    return OpCount(method, backend, steps, dict(top_level_operators(prof.events())))


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default="builtin:default")
    ap.add_argument("--data-factor", type=int, default=None)
    ap.add_argument("--methods", nargs="+", default=list(DEFAULT_METHODS))
    ap.add_argument("--backend", default="cpp", choices=["torch", "cpp"])
    ap.add_argument("--warmup", type=int, default=20, help="steps trained before counting")
    ap.add_argument("--steps", type=int, default=10, help="steps counted")
    ap.add_argument("--max-steps", type=int, default=300, help="run length the schedule is resolved for")
    ap.add_argument("--top", type=int, default=10, help="the most frequent operators listed per method")
    a = ap.parse_args(argv)
    print(f"# torch {torch.__version__}; {a.data}; backend {a.backend}; top-level operators per training step "
          f"(steps {a.warmup}-{a.warmup + a.steps - 1} of a {a.max_steps}-step schedule, one thread)")
    print("| method | operators per step | most frequent (calls per step) |")
    print("|---|---|---|")
    for method in a.methods:
        r = count_operators(method, a.data, a.backend, a.warmup, a.steps, a.max_steps, data_factor=a.data_factor)
        top = sorted(r.by_name.items(), key=lambda kv: (-kv[1], kv[0]))[: a.top]
        listed = ", ".join(f"{name.removeprefix('aten::')} {n / r.steps:.1f}" for name, n in top)
        print(f"| {method} | {r.per_step:.1f} | {listed} |", flush=True)


if __name__ == "__main__":
    main()
