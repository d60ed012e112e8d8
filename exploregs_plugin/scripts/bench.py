"""eg-bench: run methods x scenes x seeds and write the paper-shaped tables and plots.

    eg-bench quick --out bench-quick                       # a few minutes
    eg-bench standard --out bench-standard --dry-run       # the plan and its estimated cost
    eg-bench --methods default seed seed50=seed --scenes builtin:farside /data/garden \\
        --seeds 0 1 --steps 2000 --override 'seed50:--strategy.seeding.n-seed 50' \\
        --scene-option 'garden:--data-factor 4' --out bench-mine
    eg-bench --spec bench.yml --out bench-mine             # the same as a YAML/JSON file
    eg-bench quick --out bench-quick --report-only         # tables from the runs already there
"""

from __future__ import annotations

import shlex
import sys
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Annotated, Literal, Optional

import tyro

from exploregs_plugin.bench.presets import PRESETS
from exploregs_plugin.bench.spec import BenchSpec
from exploregs_plugin.io.config_files import unset
from exploregs_plugin.data.dataparser import BUILTIN_PREFIX, another_commands_input
from exploregs_plugin.data.errors import DataError
from exploregs_plugin.runtime.device import resolve_device
from exploregs_plugin.scripts import parse_cli, run_cli

PresetName = Literal[tuple(PRESETS)]  # type: ignore[valid-type]  # every key of bench.presets.PRESETS


FROM_PRESET = "the preset's or spec file's"


@dataclass
class BenchCommand:
    """Run methods x scenes x seeds with a common step budget and write results.md, results.csv,
    summary.csv, results.json and PNG plots. Finished runs in OUT are reused; unfinished ones are
    resumed or redone."""

    preset: Annotated[tyro.conf.Positional[Optional[PresetName]], unset("none, the options alone")] = None
    """Start from a preset: quick (minutes), standard (built-in Blur-Trap scenes, ~2 h), real
    (../shared/scenes), full (the paper's 30k-step schedule on them, on a CPU: ~13 h with --jobs
    2, resumable), full-explore (MCMC with exploration against MCMC at that schedule), cap-sweep
    (fixed caps against the automatic cap at that schedule), real-gpu (the same recipe at full
    resolution, for a GPU), dynamic (the 4D
    methods on the built-in dynamic scene, docs/dynamic.md), dnerf (the 4D and two static methods on
    the D-NeRF lego in ../shared/scenes), branch-ablation, depth-supervision, split-ablation (the
    paper's ablations, docs/analysis.md), time-to-quality (training seconds to test PSNRs of
    coarse-to-fine, the short schedule and Seed+Split against the default, beer and fox at --data-factor 4 and
    builtin:default). Options below change it."""
    out: Path = Path("bench-results")
    """Results folder: tables and plots here, each run in OUT/runs/<scene>/<entry>/seed<k>/."""
    spec: Annotated[Optional[Path], unset("none")] = None
    """YAML or JSON spec file (keys: preset, steps, seeds, eval_count, baseline, methods, scenes)."""
    methods: Annotated[Optional[tuple[str, ...]], unset(FROM_PRESET)] = None
    """Entries: named (default, default-relaxed-prune, default-lowthresh, seed, split, seedsplit,
    ray, mcmc, mcmc-ray), a registered method (exploregs-seed), or NAME=METHOD for a new row."""
    scenes: Annotated[Optional[tuple[str, ...]], unset(FROM_PRESET)] = None
    """Scenes: builtin:NAME, a dataset path, or NAME=DATA."""
    seeds: Annotated[Optional[tuple[int, ...]], unset(f"{FROM_PRESET}, else 0")] = None
    """Seeds (each run uses one)."""
    steps: Annotated[Optional[int], unset(f"{FROM_PRESET}, else 1000")] = None
    """Common step budget of every run."""
    eval_count: Annotated[Optional[int], unset(f"{FROM_PRESET}, else 5")] = None
    """Test evaluations per run (points of the PSNR-against-time curves)."""
    baseline: Annotated[Optional[str], unset(f"{FROM_PRESET}, else default")] = None
    """Entry that the paired differences are taken against."""
    override: Annotated[tuple[str, ...], tyro.conf.UseAppendAction] = ()
    """Per-entry eg-train arguments, 'ENTRY:ARGS', e.g. 'seed:--strategy.seeding.n-seed 50'."""
    scene_option: Annotated[tuple[str, ...], tyro.conf.UseAppendAction] = ()
    """Per-scene eg-train arguments, 'SCENE:ARGS', e.g. 'beer:--data-factor 8'."""
    data_factor: Annotated[Optional[int], unset("none added")] = None
    """Add --data-factor N to every scene."""
    device: str = "auto"
    """Device of every run: auto (CUDA when available, else CPU), cpu, cuda or cuda:N. Resolved
    here and recorded in each run's config, so runs made on one device are not reused for another."""
    jobs: int = 1
    """Runs in parallel, each with cores // jobs torch threads (timings then share the CPU)."""
    retries: int = 1
    """Fresh attempts of a failed run before it is recorded as failed."""
    timeout: Annotated[Optional[float], unset("no limit")] = None
    """Seconds after which a run is stopped and recorded as failed."""
    report_only: bool = False
    """Train nothing: write the tables and plots from the runs already in OUT."""
    dry_run: bool = False
    """Print the plan and the estimated cost, then stop."""


def describe(spec: BenchSpec, results: Path) -> list[str]:
    """The plan in a few lines: entries, scenes, runs, notes and the estimated cost."""
    from exploregs_plugin.bench.estimate import estimate_seconds
    from exploregs_plugin.bench.runner import is_finished

    n = len(spec.runs())
    fewer = " (fewer for some methods)" if n < len(spec.entries) * len(spec.scenes) * len(spec.seeds) else ""
    lines = [f"bench {spec.name}: {len(spec.entries)} methods x {len(spec.scenes)} scenes x "
             f"{len(spec.seeds)} seeds{fewer} = {n} runs of {spec.steps} steps",
             "  methods: " + ", ".join(e.name + (f" [{' '.join(e.overrides)}]" if e.overrides else "")
                                       for e in spec.entries),
             "  scenes: " + ", ".join(f"{s.name} ({s.data}{' ' + ' '.join(s.options) if s.options else ''})"
                                      for s in spec.scenes)]
    lines += [f"  note: {note}" for note in spec.notes]
    todo = [run for run in spec.runs() if not is_finished(spec, results, *run)]
    if len(todo) < len(spec.runs()):
        lines.append(f"  {len(spec.runs()) - len(todo)} runs already finished in {results} are reused")
    seconds, how = estimate_seconds(spec, todo)
    if seconds is None:
        lines.append(f"  estimate: {how}")
    else:
        lines.append(f"  estimate: ~{seconds / 60:.0f} min for {len(todo)} runs with one job at the measured rates "
                     f"({how})")
    return lines


def check_scenes(spec: BenchSpec) -> None:
    """A scene path that is missing, a run folder or a PLY is one line before any run starts (each
    run would otherwise fail on it in turn)."""
    for scene in spec.scenes:
        if scene.data.startswith(BUILTIN_PREFIX):
            continue
        path = Path(scene.data).expanduser()
        problem = "path does not exist (and is not builtin:NAME)" if not path.exists() else another_commands_input(path)
        if problem is not None:
            raise DataError(f"scene {scene.data}", problem)


def main(argv: list[str]) -> dict | None:
    from exploregs_plugin.bench.report import report
    from exploregs_plugin.bench.runner import RunOptions, execute
    from exploregs_plugin.bench.specfile import compose

    cmd = parse_cli("eg-bench", BenchCommand, __doc__.split("\n")[0], argv)
    spec = compose(cmd.preset, cmd.spec, cmd.methods, cmd.scenes, cmd.seeds, cmd.steps, cmd.eval_count,
                   cmd.baseline, cmd.override, cmd.scene_option, cmd.data_factor)
    spec = replace(spec, device=str(resolve_device(cmd.device)))
    if not cmd.report_only:
        check_scenes(spec)
    for line in describe(spec, cmd.out):
        print(line, file=sys.stderr)
    if cmd.dry_run:
        return None
    options = RunOptions(jobs=cmd.jobs, retries=cmd.retries, timeout=cmd.timeout, train=not cmd.report_only)
    try:
        records = execute(spec, cmd.out, options)
    except KeyboardInterrupt:
        print("eg-bench: interrupted; run the same command again to continue (finished runs are reused, "
              "the interrupted one resumes from its checkpoint)", file=sys.stderr)
        raise SystemExit(130) from None
    payload = report(cmd.out, spec, records, command=shlex.join(["eg-bench", *argv]))
    failed = sum(r.status == "failed" for r in records)
    print("\n".join(["time to quality (training seconds to each test PSNR; ratio to "
                     f"{spec.baseline!r}):", ""] + payload["time_to_quality_md"]))
    print(f"results: {cmd.out / 'results.md'} ({len(records)} runs, {failed} failed)", file=sys.stderr)
    return payload


def entrypoint() -> None:
    run_cli("eg-bench", main, sys.argv[1:])


if __name__ == "__main__":
    entrypoint()
