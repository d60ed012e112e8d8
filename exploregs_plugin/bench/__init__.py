"""eg-bench: methods x scenes x seeds through the normal trainer, the paper's tables and plots.

    from exploregs_plugin.bench import preset, run_bench
    payload = run_bench(preset("quick"), Path("bench-quick"))
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from exploregs_plugin.bench.plots import write_plots
from exploregs_plugin.bench.presets import PRESETS, named_entries, preset
from exploregs_plugin.bench.runner import RunOptions, RunRecord, execute, run_dir_for
from exploregs_plugin.bench.spec import BenchEntry, BenchScene, BenchSpec, BenchSpecError
from exploregs_plugin.bench.specfile import compose
from exploregs_plugin.bench.tables import write_tables

__all__ = [
    "BenchEntry", "BenchScene", "BenchSpec", "BenchSpecError", "PRESETS", "RunOptions", "RunRecord",
    "compose", "execute", "named_entries", "preset", "report", "run_bench", "run_dir_for",
]


def report(results: Path, spec: BenchSpec, records: list[RunRecord], command: str | None = None) -> dict[str, Any]:
    """Write the tables (results.md/.csv/.json, summary.csv) and the PNG plots; returns results.json's content."""
    payload = write_tables(results, spec, records, command)
    write_plots(results, spec, payload)
    return payload


def run_bench(spec: BenchSpec, results: Path, options: RunOptions | None = None,
              command: str | None = None) -> dict[str, Any]:
    """Run (or reuse) every run of ``spec`` under ``results/runs/`` and write the report."""
    records = execute(spec, Path(results), options)
    return report(Path(results), spec, records, command)
