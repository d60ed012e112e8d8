"""Benchmarks and experiment harnesses, in one home.

eg-bench (methods x scenes x seeds through the normal trainer, the paper's tables and plots)::

    from exploregs_plugin.bench import preset, run_bench
    payload = run_bench(preset("quick"), Path("bench-quick"))

and the component benchmarks, each a script that prints a table: ``python -m
exploregs_plugin.bench.rasterizer`` (speed, memory and error of the rasterizer),
``python -m exploregs_plugin.bench.opcost`` (per-element cost of torch ops) and ``python -m
exploregs_plugin.bench.viewer`` (training speed with the live viewer). Names are imported on
first use, so a component benchmark does not load the trainer.
"""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS = {
    "BenchEntry": "spec", "BenchScene": "spec", "BenchSpec": "spec", "BenchSpecError": "spec",
    "PRESETS": "presets", "named_entries": "presets", "preset": "presets",
    "RunOptions": "runner", "RunRecord": "runner", "execute": "runner", "run_dir_for": "runner",
    "compose": "specfile", "report": "report", "run_bench": "report",
}
__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    if name not in _EXPORTS:
        raise AttributeError(f"module 'exploregs_plugin.bench' has no attribute {name!r}")
    return getattr(importlib.import_module(f"exploregs_plugin.bench.{_EXPORTS[name]}"), name)
