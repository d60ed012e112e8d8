"""eg-bench end to end on the tiny scene: tables and plots, numbers equal to each run's
metrics.json, reuse of finished runs, resume of unfinished ones, failed runs kept in the tables."""

from __future__ import annotations

import csv
import json
from dataclasses import replace
from pathlib import Path

import pytest
from PIL import Image

from exploregs_plugin.bench.report import run_bench
from exploregs_plugin.bench.runner import RunOptions, run_dir_for
from exploregs_plugin.bench.spec import BenchEntry, BenchScene, BenchSpec
from exploregs_plugin.bench.presets import named_entries

STEPS = 20
TINY = BenchScene("tiny", "builtin:tiny", ("--schedule.min-refine-every", "5"))
"""Densify (and seed) at step 5 of the 20, so the two methods differ."""


def tiny_spec(*extra: BenchEntry, scenes: tuple[BenchScene, ...] | None = None) -> BenchSpec:
    named = named_entries()
    return BenchSpec(entries=(named["default"], named["seed"], *extra),
                     scenes=scenes or (TINY,),
                     seeds=(0,), steps=STEPS, eval_count=2, name="test")


@pytest.fixture(scope="module", autouse=True)
def one_thread_per_run():
    """Every run's process computes on one thread (OMP_NUM_THREADS, which eg-train honours), for
    this module: on a scene this small a second thread only waits for the first, and on a busy
    machine it spins while it waits (runtime/threads.py); the thread count changes no result."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("OMP_NUM_THREADS", "1")
        yield


def _worker_in_this_process(cmd, stdout, stderr, timeout):
    """``subprocess.run`` of a run's worker (``python -m exploregs_plugin.bench.worker RUN_DIR``) as
    a call of the worker's main in this process, on one thread, its output into the run's bench.log
    as the process's would go."""
    import contextlib
    import subprocess

    import torch

    from exploregs_plugin.bench import worker

    assert cmd[1:3] == ["-m", "exploregs_plugin.bench.worker"] and stderr is subprocess.STDOUT, cmd
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stdout):
            returncode = worker.main(cmd[3:])
    finally:
        torch.set_num_threads(threads)
    return subprocess.CompletedProcess(cmd, returncode)


def _runner_subprocess(run):
    """What bench/runner.py reaches as ``subprocess``, with ``run`` in place of subprocess.run."""
    import subprocess
    from types import SimpleNamespace

    return SimpleNamespace(run=run, STDOUT=subprocess.STDOUT, TimeoutExpired=subprocess.TimeoutExpired)


@pytest.fixture(scope="module")
def bench(tmp_path_factory, tiny_scene_dir, one_thread_per_run):
    """The two-run bench, end to end. The ``default`` run starts its worker as the bench does, a real
    process (what proves that ``python -m exploregs_plugin.bench.worker`` trains a run and reports
    it); the ``seed`` run's worker is called in this process, which saves an interpreter and a
    torch import (2-3 s of CPU) and changes nothing the tests read (its folder, metrics and log)."""
    import subprocess

    from exploregs_plugin.bench import runner

    processes: list[Path] = []

    def default_in_a_process(cmd, stdout, stderr, timeout):
        if Path(cmd[3]) == run_dir_for(out, "tiny", "default", 0):
            processes.append(Path(cmd[3]))
            return subprocess.run(cmd, stdout=stdout, stderr=stderr, timeout=timeout)
        return _worker_in_this_process(cmd, stdout, stderr, timeout)

    out = tmp_path_factory.mktemp("bench")
    logs: list[str] = []
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(runner, "subprocess", _runner_subprocess(default_in_a_process))
        payload = run_bench(tiny_spec(), out, RunOptions(log=logs.append), command="eg-bench (test)")
    assert set(processes) == {run_dir_for(out, "tiny", "default", 0)}  # the default run did start a real process
    return out, payload, logs


@pytest.fixture()
def workers_in_this_process(monkeypatch):
    """The bench starts each run's worker as a call of the worker's main in this process
    (``_worker_in_this_process``): for a test of what the bench decides and records rather than of
    how a run is started, which saves an interpreter and a torch import per run. The ``default``
    run of ``bench`` starts a real process."""
    from exploregs_plugin.bench import runner

    monkeypatch.setattr(runner, "subprocess", _runner_subprocess(_worker_in_this_process))


def _metrics(out: Path, entry: str) -> dict:
    return json.loads((run_dir_for(out, "tiny", entry, 0) / "metrics.json").read_text())


def test_writes_tables_and_plots(bench):
    out, payload, logs = bench
    for name in ("results.md", "results.csv", "summary.csv", "results.json", "psnr_vs_gaussians.png",
                 "psnr_vs_time_tiny.png"):
        assert (out / name).is_file(), name
    for png in out.glob("*.png"):
        with Image.open(png) as im:
            assert im.size[0] > 200 and im.size[1] > 200
    assert [r["status"] for r in payload["runs"]] == ["done", "done"]
    assert all("trained in" in line for line in logs)
    md = (out / "results.md").read_text()
    for heading in ("## Test image quality", "## Paired differences", "## Region PSNR", "## Gaussians"):
        assert heading in md


def test_table_numbers_equal_each_runs_metrics(bench):
    out, payload, _ = bench
    rows = {r["entry"]: r for r in csv.DictReader(open(out / "results.csv"))}
    md = (out / "results.md").read_text()
    quality = md.split("## Test image quality")[1].split("##")[0]
    for entry in ("default", "seed"):
        m = _metrics(out, entry)
        row = rows[entry]
        assert float(row["psnr"]) == pytest.approx(m["psnr"], abs=1e-9)
        assert float(row["ssim"]) == pytest.approx(m["ssim"], abs=1e-9)
        assert int(float(row["num_gaussians"])) == m["num_gaussians"]
        assert float(row["train_seconds"]) == pytest.approx(m["train_seconds"], abs=1e-9)
        for region in ("far", "occluded", "other"):
            assert float(row[f"region_{region}"]) == pytest.approx(m["region_psnr"][region], abs=1e-9)
        line = next(ln for ln in quality.splitlines() if ln.startswith(f"| {entry} |"))
        assert float(row["dssim"]) == pytest.approx(m["dssim"], abs=1e-9)
        assert m["dssim"] == pytest.approx((1 - m["ms_ssim"]) / 2)
        # one seed: no ± ; LPIPS n/a where its weights are not installed
        lpips = "n/a" if m["lpips"] is None else f"{m['lpips']:.4f}"
        assert f"| {m['psnr']:.2f} | {m['ssim']:.4f} | {m['dssim']:.4f} | {lpips} |" in line
        run = next(r for r in payload["runs"] if r["entry"] == entry)
        assert run["history"] == m["history"] and len(run["history"]) == 2
    # the paired difference is seed's PSNR minus default's, on the same seed
    seed_line = next(ln for ln in quality.splitlines() if ln.startswith("| seed |"))
    diff = _metrics(out, "seed")["psnr"] - _metrics(out, "default")["psnr"]
    assert seed_line.rstrip(" |").endswith(f"{diff:+.2f}")
    summary = {s["entry"]: s for s in payload["summary"]}
    assert summary["seed"]["paired"]["psnr"]["mean"] == pytest.approx(diff, abs=1e-9)
    assert summary["seed"]["paired"]["psnr"]["n"] == 1


def test_a_dry_run_counts_the_finished_runs_of_the_same_config_only(bench):
    from exploregs_plugin.scripts.bench import describe

    out, _, _ = bench
    assert "  2 runs already finished in " + str(out) + " are reused" in describe(tiny_spec(), out)
    # another step count is another config: nothing to reuse (a folder's metrics.json alone is not enough)
    assert not any("already finished" in line for line in describe(replace(tiny_spec(), steps=STEPS + 1), out))
    # a folder without metrics.json is unfinished, whatever its config
    assert not any("already finished" in line for line in describe(tiny_spec(), out / "elsewhere"))


def test_rerun_reuses_finished_runs_and_resumes_unfinished(bench, workers_in_this_process):
    out, payload, _ = bench
    default_dir, seed_dir = run_dir_for(out, "tiny", "default", 0), run_dir_for(out, "tiny", "seed", 0)
    stamp = (default_dir / "metrics.json").stat().st_mtime_ns
    log_before = (default_dir / "bench.log").read_text()
    seed_metrics = _metrics(out, "seed")
    (seed_dir / "metrics.json").unlink()  # as if it stopped after its last checkpoint
    logs: list[str] = []
    again = run_bench(tiny_spec(), out, RunOptions(log=logs.append))
    assert (default_dir / "metrics.json").stat().st_mtime_ns == stamp
    assert (default_dir / "bench.log").read_text() == log_before  # no process was started for it
    assert "reused" in logs[0] and "trained in" in logs[1]
    # a resumed run reports its whole training time (metrics.json sums it over resumes), not this call's
    resumed_seconds = _metrics(out, "seed")["wall_seconds"]
    assert f"resumed, trained in {resumed_seconds:.0f} s in all (" in logs[1]
    commands = [ln for ln in (seed_dir / "bench.log").read_text().splitlines() if ln.startswith("$ ")]
    assert len(commands) == 2 and commands[1].endswith(" --resume")
    resumed = _metrics(out, "seed")
    assert resumed["psnr"] == pytest.approx(seed_metrics["psnr"], abs=1e-6)
    assert resumed["num_gaussians"] == seed_metrics["num_gaussians"]
    assert [r["psnr"] for r in again["runs"]] == [r["psnr"] for r in payload["runs"]]


def test_failing_runs_appear_as_failed(bench, tmp_path, workers_in_this_process):
    out, _, _ = bench
    named = named_entries()
    bad = BenchEntry("bad-override", "exploregs-default", ("--strategy.no-such-field", "1"))
    spec = replace(tiny_spec(), entries=(named["default"], bad),
                   scenes=(TINY, BenchScene("gone", str(tmp_path / "missing"))))
    logs: list[str] = []
    payload = run_bench(spec, out, RunOptions(log=logs.append))
    runs = {(r["scene"], r["entry"]): r for r in payload["runs"]}
    assert len(runs) == 4  # nothing dropped
    bad_run = runs[("tiny", "bad-override")]
    assert bad_run["status"] == "failed" and "no-such-field" in bad_run["error"]
    # a crash inside the run's worker: tried, retried from scratch, then recorded
    gone = runs[("gone", "default")]
    assert gone["status"] == "failed" and gone["attempts"] == 2 and "missing" in gone["error"]
    state = json.loads((run_dir_for(out, "gone", "default", 0) / "bench_state.json").read_text())
    assert state["status"] == "failed" and state["error"] == gone["error"]
    assert runs[("tiny", "default")]["status"] == "done" and "reused" in logs[0]
    md = (out / "results.md").read_text()
    quality = md.split("## Test image quality")[1].split("##")[0]
    assert "| bad-override | failed | failed | failed | failed | failed | failed | failed | failed |" in quality
    assert "Failed runs:" in md and "no-such-field" in md.split("Failed runs:")[1]
    assert "| gone | default | 0 | 2 |" in md
    assert "4 runs: 1 finished, 3 failed" in md
    rows = list(csv.DictReader(open(out / "results.csv")))
    assert sum(r["status"] == "failed" for r in rows) == 3


def test_parallel_runs_parse_overrides_in_the_main_thread_and_lose_no_output(bench, monkeypatch, capsys):
    # Parsing an entry's overrides swaps the process-wide stderr for a moment; done inside the
    # worker threads it swallowed other threads' progress lines and could leave stderr captured.
    import sys
    import threading

    from exploregs_plugin.bench import runner

    out, _, _ = bench
    named = named_entries()
    entries = tuple(replace(named["default"], name=f"default-{i}", overrides=("--strategy.prune-opa", f"0.00{i}"))
                    for i in range(1, 7))
    spec = replace(tiny_spec(), entries=entries)
    threads: list[threading.Thread] = []
    build = runner.build_config

    def recording_build(*args, **kwargs):
        threads.append(threading.current_thread())
        return build(*args, **kwargs)

    monkeypatch.setattr(runner, "build_config", recording_build)
    stderr = sys.stderr
    records = runner.execute(spec, out, RunOptions(jobs=3, train=False))
    assert len(records) == 6 and all(r.status == "not run" or r.metrics is None for r in records)
    assert len(threads) == 6 and all(t is threading.main_thread() for t in threads)
    assert sys.stderr is stderr
    printed = [ln for ln in capsys.readouterr().err.splitlines() if ln.startswith("[")]
    assert sorted(ln.split("] ")[0] for ln in printed) == [f"[{k}/6" for k in range(1, 7)]
    assert sorted(ln.split("] ")[1] for ln in printed) == [f"tiny/default-{i}/seed0: not run" for i in range(1, 7)]


def test_real_gpu_preset_at_tiny_scale_matches_counts_through_result_references(tmp_path, tiny_scene_dir,
                                                                              workers_in_this_process):
    from exploregs_plugin.bench.presets import REAL_GPU_STEPS, real_gpu
    from exploregs_plugin.bench.spec import BenchSpecError, build_config
    from exploregs_plugin.io.config_files import load_config

    root = tmp_path / "scenes"
    (root / "beer").mkdir(parents=True)
    spec = real_gpu(root)
    assert spec.name == "real-gpu" and spec.steps == REAL_GPU_STEPS == 30_000 and spec.seeds == (0, 1, 2)
    assert [s.name for s in spec.scenes] == ["beer"] and "fox" in spec.notes[0]
    config = build_config(replace(spec, device="cpu"), spec.scenes[0], spec.entry("seedsplit"), 0, tmp_path / "x")
    schedule = config.schedule.resolve(config.max_steps)
    # the 3DGS schedule, unscaled
    assert (schedule.refine_start, schedule.refine_stop, schedule.refine_every, schedule.reset_every,
            schedule.sh_degree_interval) == (500, 15_000, 100, 3_000, 1_000)
    assert config.pipeline.model.sh_degree == 3 and config.pipeline.datamanager.test_every == 8
    assert config.pipeline.strategy.budget == "paper" and config.pipeline.datamanager.data_factor == 1
    assert spec.entry("mcmc").depends_on() == {"default"}
    assert spec.entry("default-lowthresh").depends_on() == {"seedsplit"}

    # the entries that give or take a count on the tiny scene, 30 steps: the dependent runs wait and
    # take the counts (the preset's other entries are runs like these, with other methods)
    linked = ("default", "seedsplit", "mcmc", "default-lowthresh")
    tiny = replace(spec, entries=tuple(spec.entry(name) for name in linked),
                   scenes=(BenchScene("tiny", "builtin:tiny", ("--schedule.min-refine-every", "10")),),
                   seeds=(0,), steps=30, eval_count=1, device="cpu")
    # a report before anything ran: the runs that wait for another one are not run, not failed
    from exploregs_plugin.bench import runner

    early = runner.execute(tiny, tmp_path / "early", RunOptions(train=False))
    assert {r.status for r in early} == {"missing"} and any(e.depends_on() for e in tiny.entries)
    logs: list[str] = []
    payload = run_bench(tiny, tmp_path / "out", RunOptions(log=logs.append))
    assert all(r["status"] == "done" for r in payload["runs"]), logs
    counts = {e.name: _metrics(tmp_path / "out", e.name)["num_gaussians"] for e in tiny.entries}
    mcmc = load_config(run_dir_for(tmp_path / "out", "tiny", "mcmc", 0) / "config.yml")
    low = load_config(run_dir_for(tmp_path / "out", "tiny", "default-lowthresh", 0) / "config.yml")
    assert mcmc.pipeline.strategy.cap_max == counts["default"]
    assert low.pipeline.strategy.cap_max == counts["seedsplit"] and counts["default-lowthresh"] <= counts["seedsplit"]
    order = [line.split("] ")[1].split(":")[0] for line in logs if line.startswith("[")]
    assert order.index("tiny/mcmc/seed0") > order.index("tiny/default/seed0")
    assert order.index("tiny/default-lowthresh/seed0") > order.index("tiny/seedsplit/seed0")

    with pytest.raises(BenchSpecError, match="uses the result of 'nope'"):
        BenchSpec(entries=(BenchEntry("a", "exploregs-mcmc", ("--strategy.cap-max", "{nope:num_gaussians}")),),
                  scenes=(TINY,))
    with pytest.raises(BenchSpecError, match="itself waits for another entry"):
        BenchSpec(entries=(BenchEntry("a", "exploregs-default"),
                           BenchEntry("b", "exploregs-mcmc", ("--strategy.cap-max", "{a:num_gaussians}")),
                           BenchEntry("c", "exploregs-mcmc", ("--strategy.cap-max", "{b:num_gaussians}"))),
                  scenes=(TINY,))


def test_a_dependent_run_starts_when_its_inputs_finish_not_after_every_other_run(tmp_path, monkeypatch):
    """Two job slots; ``slow`` and ``fast`` are independent, ``after`` uses ``fast``'s count. ``after``
    must start (its config built once ``fast`` has finished) while ``slow`` still runs: ``slow``
    waits for that start, so a scheduler that holds ``after`` back until every independent run has
    finished leaves ``slow`` to time out."""
    import threading

    from exploregs_plugin.bench import runner

    spec = BenchSpec(entries=(BenchEntry("slow", "exploregs-default"), BenchEntry("fast", "exploregs-default"),
                              BenchEntry("after", "exploregs-mcmc", ("--strategy.cap-max", "{fast:num_gaussians}"))),
                     scenes=(TINY,), seeds=(0, 1), steps=STEPS, name="test")
    finished: set[tuple[str, int]] = set()
    built_after: list[tuple[int, bool]] = []
    after_started = {0: threading.Event(), 1: threading.Event()}
    slow_saw_after: dict[int, bool] = {}

    def fake_config(spec, results, scene, entry, seed):
        if entry.name == "after":
            built_after.append((seed, ("fast", seed) in finished))
        return entry.name

    def fake_run(spec, results, scene, entry, seed, options, prepared):
        assert prepared == entry.name
        if entry.name == "slow":
            slow_saw_after[seed] = after_started[seed].wait(timeout=10)
        if entry.name == "after":
            after_started[seed].set()
        finished.add((entry.name, seed))
        return runner.RunRecord(scene.name, entry.name, seed, tmp_path, status="done", metrics={"psnr": 1.0})

    monkeypatch.setattr(runner, "_config_or_error", fake_config)
    monkeypatch.setattr(runner, "run_one", fake_run)
    logs: list[str] = []
    records = runner.execute(spec, tmp_path, RunOptions(jobs=2, log=logs.append))
    assert [(r.entry, r.seed) for r in records] == [(e, s) for s in (0, 1) for e in ("slow", "fast", "after")]
    assert sorted(built_after) == [(0, True), (1, True)]
    assert slow_saw_after == {0: True, 1: True}
    assert len([ln for ln in logs if ln.startswith("[")]) == 6
