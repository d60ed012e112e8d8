"""A whole benchmark: run (or reuse) every run of a spec, then write its tables and plots."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from exploregs_plugin.bench.plots import write_plots
from exploregs_plugin.bench.runner import RunOptions, RunRecord, execute
from exploregs_plugin.bench.spec import BenchSpec
from exploregs_plugin.bench.tables import write_tables


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
