"""Running a bench: one subprocess per run, each in ``RESULTS/runs/<scene>/<entry>/seed<k>/``.

Resumability, per run folder:
- ``metrics.json`` present and the same config (``bench_job.yml`` against the requested config,
  :func:`configs_match`): reused;
- checkpoints present, same config, no metrics: resumed from the newest checkpoint;
- anything else (new, config changed, a failed or unreadable earlier attempt): trained afresh.
A run that fails is tried again from scratch ``retries`` times; if it still fails it is recorded
as failed with its error (``bench_state.json``) and shown so in every table.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import threading
import time
from concurrent.futures import FIRST_COMPLETED, Future, ThreadPoolExecutor, wait
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Callable

from exploregs_plugin.bench.spec import (
    BenchEntry,
    BenchScene,
    BenchSpec,
    BenchSpecError,
    build_config,
    comparable,
    config_fingerprint,
    configs_match,
)
from exploregs_plugin.bench.files import ERROR_NAME, JOB_NAME, LOG_NAME, METRICS_NAME, STATE_NAME
from exploregs_plugin.io.atomic import atomic_write_text
from exploregs_plugin.io.checkpoint import list_checkpoints
from exploregs_plugin.engine.trainer import TrainerConfig

RUNS_DIR = "runs"


@dataclass
class RunRecord:
    """The outcome of one (scene, entry, seed)."""

    scene: str
    entry: str
    seed: int
    run_dir: Path
    status: str = "missing"
    """``done``, ``failed`` or ``missing`` (not run: report-only on a folder without it)."""
    error: str | None = None
    metrics: dict[str, Any] | None = None
    trained: bool = False
    """True when this invocation trained (or resumed) it; False when reused."""
    resumed: bool = False
    """True when this invocation went on from the run's checkpoint instead of starting it."""
    attempts: int = 0
    wall_seconds: float = 0.0
    """Wall-clock seconds of this invocation's subprocesses (start-up and evaluation included)."""


@dataclass
class RunOptions:
    jobs: int = 1
    """Runs in parallel (each gets cores // jobs torch threads)."""
    retries: int = 1
    """Fresh attempts after a failure before a run is recorded as failed."""
    timeout: float | None = None
    """Seconds after which a run is stopped and counts as failed (None: no limit)."""
    train: bool = True
    """False: only collect what the run folders hold (report-only)."""
    log: Callable[[str], None] = field(default=lambda msg: print(msg, file=sys.stderr, flush=True))


def run_dir_for(results: Path, scene: str, entry: str, seed: int) -> Path:
    return Path(results) / RUNS_DIR / scene / entry / f"seed{seed}"


def read_json(path: Path) -> dict[str, Any] | None:
    try:
        return json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return None


def _write_state(run_dir: Path, **state: Any) -> None:
    atomic_write_text(run_dir / STATE_NAME, json.dumps(state, indent=2))


def _fresh_folder(run_dir: Path) -> None:
    if run_dir.exists():
        shutil.rmtree(run_dir)
    run_dir.mkdir(parents=True)


def _launch(run_dir: Path, resume: bool, timeout: float | None) -> tuple[int, str | None]:
    """Run the worker; returns (exit code, error line or None)."""
    (run_dir / ERROR_NAME).unlink(missing_ok=True)
    cmd = [sys.executable, "-m", "exploregs_plugin.bench.worker", str(run_dir)] + (["--resume"] if resume else [])
    with open(run_dir / LOG_NAME, "a") as log:
        log.write(f"$ {' '.join(cmd)}\n")
        log.flush()
        try:
            rc = subprocess.run(cmd, stdout=log, stderr=subprocess.STDOUT, timeout=timeout).returncode
        except subprocess.TimeoutExpired:
            return -1, f"timed out after {timeout:g} s"
    if rc == 130:  # Ctrl-C reached the worker too: it checkpointed; stop the bench, do not retry
        raise KeyboardInterrupt(f"interrupted during {run_dir}")
    if rc == 0 and (run_dir / METRICS_NAME).is_file():
        return 0, None
    error_file = run_dir / ERROR_NAME
    if error_file.is_file():
        return rc, error_file.read_text().strip()
    tail = [ln for ln in (run_dir / LOG_NAME).read_text().splitlines() if ln.strip()][-1:]
    return rc, f"exit code {rc}" + (f": {tail[0].strip()}" if tail else "") + (" (no metrics.json)" if rc == 0 else "")


def same_config(run_dir: Path, config: Any) -> bool:
    """Whether the run folder was made for ``config`` (its bench_job.yml matches, see configs_match)."""
    import yaml

    from exploregs_plugin.io.config_files import config_to_dict, read_yaml, upgraded

    try:
        old = read_yaml((Path(run_dir) / JOB_NAME).read_text())
    except (OSError, yaml.YAMLError):
        return False
    return isinstance(old, dict) and configs_match(comparable(upgraded(old)), comparable(config_to_dict(config)))


def _config_or_error(spec: BenchSpec, results: Path, scene: BenchScene, entry: BenchEntry,
                     seed: int) -> TrainerConfig | BenchSpecError:
    def value_of(ref: str, field: str) -> Any:
        """A result of entry ``ref``'s run on this scene and seed (it ran before this one)."""
        metrics = read_json(run_dir_for(results, scene.name, ref, seed) / METRICS_NAME) or {}
        if field not in metrics:
            raise BenchSpecError(f"entry {entry.name!r} needs {field} of {ref!r} on {scene.name} seed {seed}, "
                                 f"which has no finished run")
        return metrics[field]

    try:
        resolved = entry.resolved(value_of) if entry.depends_on() else entry
        return build_config(spec, scene, resolved, seed, run_dir_for(results, scene.name, entry.name, seed))
    except BenchSpecError as err:
        return err


def is_finished(spec: BenchSpec, results: Path, scene: BenchScene, entry: BenchEntry, seed: int) -> bool:
    """True when the run folder holds metrics.json of this config (it would be reused). A folder
    without metrics.json is unfinished whatever its config, so the config (a parse of the entry's
    overrides, tenths of a second each: a dry run of a large preset asks for every run) is built
    only for the folders that have one."""
    if not (run_dir_for(results, scene.name, entry.name, seed) / METRICS_NAME).is_file():
        return False
    config = _config_or_error(spec, results, scene, entry, seed)
    if isinstance(config, BenchSpecError):
        return False
    return (config.run_dir / METRICS_NAME).is_file() and same_config(config.run_dir, config)


def run_one(spec: BenchSpec, results: Path, scene: BenchScene, entry: BenchEntry, seed: int,
            options: RunOptions, prepared: TrainerConfig | BenchSpecError | None = None) -> RunRecord:
    """Run or reuse one run. ``prepared``: its config (or the error building it), when the
    caller built it already."""
    run_dir = run_dir_for(results, scene.name, entry.name, seed)
    record = RunRecord(scene.name, entry.name, seed, run_dir)
    config = prepared if prepared is not None else _config_or_error(spec, results, scene, entry, seed)
    if isinstance(config, BenchSpecError):
        if options.train:  # a report alone leaves a run that waits for another one "not run"
            record.status, record.error = "failed", str(config)
        return record
    fingerprint = config_fingerprint(config)
    state = read_json(run_dir / STATE_NAME) or {}
    same = same_config(run_dir, config)
    metrics = read_json(run_dir / METRICS_NAME)
    if same and metrics is not None:
        record.status, record.metrics, record.attempts = "done", metrics, int(state.get("attempts", 0))
        return record
    if not options.train:
        if same and state.get("status") == "failed":
            record.status, record.error, record.attempts = "failed", state.get("error"), int(state.get("attempts", 0))
        return record
    if options.jobs > 1:
        config = replace(config, num_threads=max(1, (os.cpu_count() or 1) // options.jobs))
    resume = same and state.get("status") != "failed" and bool(list_checkpoints(run_dir)) \
        and (run_dir / "config.yml").is_file()
    start = time.perf_counter()
    for attempt in range(1 + max(0, options.retries)):
        if not resume:
            from exploregs_plugin.io.config_files import save_config

            _fresh_folder(run_dir)
            save_config(config, run_dir / JOB_NAME)
        _write_state(run_dir, fingerprint=fingerprint, status="running", attempts=attempt + 1)
        rc, error = _launch(run_dir, resume, options.timeout)
        record.attempts, record.resumed = attempt + 1, resume
        if error is None:
            record.status, record.metrics, record.error = "done", read_json(run_dir / METRICS_NAME), None
            _write_state(run_dir, fingerprint=fingerprint, status="done", attempts=attempt + 1)
            break
        what = "resumed run" if resume else "run"
        options.log(f"  {scene.name}/{entry.name}/seed{seed}: {what} failed ({error})"
                    + ("; retrying from scratch" if attempt < options.retries else ""))
        record.status, record.error = "failed", error
        _write_state(run_dir, fingerprint=fingerprint, status="failed", attempts=attempt + 1, error=error)
        resume = False
    record.trained = True
    record.wall_seconds = time.perf_counter() - start
    return record


def _needs(plan: list[tuple[BenchScene, BenchEntry, int]]) -> dict[int, set[int]]:
    """For each run of ``plan``, the runs whose results its overrides use: the referenced entries'
    runs on the same scene and seed (a reference the plan does not run is not waited for; building
    the config then reports it)."""
    where = {(scene.name, entry.name, seed): i for i, (scene, entry, seed) in enumerate(plan)}
    return {i: {where[(scene.name, ref, seed)] for ref in entry.depends_on() if (scene.name, ref, seed) in where}
            for i, (scene, entry, seed) in enumerate(plan)}


def execute(spec: BenchSpec, results: Path, options: RunOptions | None = None) -> list[RunRecord]:
    """Run (or reuse) every run of ``spec``; returns one record per (scene, entry, seed) in spec order.

    A run whose overrides use another run's result (``{ENTRY:num_gaussians}``) starts as soon as
    that run has finished, not after the whole bench's other runs: a long independent run does not
    hold a free job slot idle."""
    options = options or RunOptions()
    if options.jobs < 1:
        raise BenchSpecError(f"jobs must be >= 1, got {options.jobs}")
    plan = spec.runs()
    # One lock for everything that prints or builds a config: parsing overrides swaps the
    # process-wide stderr for a moment (to catch tyro's message), which would swallow a line
    # another thread prints meanwhile. Configs are built here, in this thread.
    lock = threading.RLock()

    def log(message: str) -> None:
        with lock:
            options.log(message)

    run_options = replace(options, log=log)
    done = {"count": 0, "trained_seconds": 0.0, "trained": 0}

    def one(index: int, prepared: TrainerConfig | BenchSpecError) -> RunRecord:
        scene, entry, seed = plan[index]
        record = run_one(spec, results, scene, entry, seed, run_options, prepared)
        with lock:
            done["count"] += 1
            if record.trained:
                done["trained"] += 1
                done["trained_seconds"] += _run_seconds(record)
            options.log(_progress_line(record, done["count"], len(plan), done, options.jobs))
        return record

    needs = _needs(plan)
    waiting = set(range(len(plan)))
    records: dict[int, RunRecord] = {}
    running: dict[Future[RunRecord], int] = {}
    with ThreadPoolExecutor(max_workers=options.jobs) as pool:
        while waiting or running:
            # in plan order, every run whose inputs are in (none waiting or running), up to the free slots
            unfinished = waiting | set(running.values())
            for i in sorted(i for i in waiting if not needs[i] & unfinished):
                if len(running) >= options.jobs:
                    break
                waiting.discard(i)
                with lock:
                    prepared = _config_or_error(spec, results, *plan[i])
                running[pool.submit(one, i, prepared)] = i
            if not running:  # the spec forbids chains, so this is a bug, not a slow bench
                raise BenchSpecError(f"runs {sorted(waiting)} wait for each other")
            finished, _ = wait(running, return_when=FIRST_COMPLETED)
            for future in finished:
                records[running.pop(future)] = future.result()
    return [records[i] for i in range(len(plan))]


def _run_seconds(record: RunRecord) -> float:
    """The run's own wall-clock seconds over all its sessions (metrics.json keeps the sum across
    resumes); this invocation's when the metrics lack it. A resumed run's invocation alone would
    make the estimate of what is left far too short."""
    seconds = (record.metrics or {}).get("wall_seconds")
    return float(seconds) if isinstance(seconds, (int, float)) and seconds > 0 else record.wall_seconds


def _progress_line(record: RunRecord, count: int, total: int, done: dict[str, Any], jobs: int) -> str:
    head = f"[{count}/{total}] {record.scene}/{record.entry}/seed{record.seed}: "
    if record.status == "done" and record.metrics is not None:
        m = record.metrics
        how = "reused"
        if record.trained:
            how = f"trained in {_run_seconds(record):.0f} s"
            if record.resumed:
                how = f"resumed, {how} in all ({record.wall_seconds:.0f} s now)"
        text = f"{how}, PSNR {m.get('psnr', float('nan')):.2f} dB, {m.get('num_gaussians')} Gaussians"
    elif record.status == "failed":
        text = f"FAILED: {record.error}"
    else:
        text = "not run"
    if done["trained"] and record.trained and count < total:
        eta = done["trained_seconds"] / done["trained"] * (total - count) / jobs
        text += f" (at most ~{eta / 60:.0f} min left)"
    return head + text
