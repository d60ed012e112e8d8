"""Batched views and data-parallel training (torch.distributed, gloo on the CPU).

The multi-process runs use ``builtin:tiny`` and one thread per rank; each launch costs a few
seconds of process start-up, so the 2-rank runs of all methods share one torchrun launch.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import pytest
import torch

from exploregs_plugin.runtime.distributed import RANK_ENV, MachineConfig, World, launched_by_torchrun, params_checksum
from exploregs_plugin.io.checkpoint import latest_checkpoint, list_checkpoints, load_checkpoint
from exploregs_plugin.method_configs import get_method
from exploregs_plugin.model.losses import photometric_loss
from exploregs_plugin.model.optim import OptimizerConfig, batch_betas
from exploregs_plugin.engine.pipeline import resolve_batch_size
from exploregs_plugin.rasterizer import RasterSettings
from exploregs_plugin.schedule import ScheduleConfig
from exploregs_plugin.scripts.launch import free_port, ranks_threads
from exploregs_plugin.scripts.train import parse_config
from exploregs_plugin.strategies.budget import resolve_budget
from exploregs_plugin.strategies.default import accumulate_grad_stats
from exploregs_plugin.strategies.observation import observe_render
from exploregs_plugin.engine.trainer import Trainer

WORKER = Path(__file__).with_name("distributed_worker.py")
METHODS = ("exploregs-default", "exploregs-seedsplit", "exploregs-mcmc", "exploregs-guided-occlusion")
STEPS = 20
"""At 2 views a step (2 ranks, or one process with --batch-size 2) the schedule of tiny_argv
densifies at steps 3, 6 and 9, resets the opacities at step 6 and stops densifying at step 10, with
a checkpoint every 5 steps (all kept): every event the comparisons need, in few steps (the densified
Gaussians are most of a run's cost)."""


def tiny_argv(method: str, run_dir: Path, *extra: str, steps: int = STEPS) -> list[str]:
    """eg-train arguments of a short tiny run with three densifications and an opacity reset."""
    return [method, "--data", "builtin:tiny", "--max-steps", str(steps), "--run-dir", str(run_dir),
            "--quiet", "--no-tensorboard", "--eval-count", "1", "--no-save-eval-images", "--num-threads", "1",
            "--checkpoint-every", "5", "--keep-checkpoints", "10", "--schedule.min-refine-every", "6",
            "--schedule.min-reset-every", "12", *extra]


METHOD_FLAGS = {"exploregs-mcmc": ("--strategy.min-opacity", "0.05")}
"""Per method, flags that make its short run take every path the comparisons cover: MCMC relocates
its dead Gaussians (at or below min-opacity), none of which a run this short has at the default."""


def method_argv(method: str, run_dir: Path, *extra: str) -> list[str]:
    """tiny_argv of a method's run in the comparisons (2 ranks against one process)."""
    return tiny_argv(method, run_dir, *METHOD_FLAGS.get(method, ()), *extra)


def worker_env() -> dict[str, str]:
    env = dict(os.environ, OMP_NUM_THREADS="1", CUDA_HOME="/nonexistent-cuda")
    for key in RANK_ENV:  # a test run under torchrun must not hand its own world to the children
        env.pop(key, None)
    return env


def torchrun(out: Path, entries: list[dict], timeout: float = 240) -> subprocess.CompletedProcess:
    command = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "2",
               str(WORKER), str(out), json.dumps(entries)]
    return subprocess.run(command, env=worker_env(), capture_output=True, text=True, timeout=timeout)


def assert_close(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor], rtol: float = 1e-5) -> None:
    assert a.keys() == b.keys()
    for k in a:
        assert a[k].shape == b[k].shape, k
        if b[k].numel() == 0:
            continue
        assert float((a[k] - b[k]).abs().max()) <= rtol * max(float(b[k].abs().max()), 1e-12), k


@pytest.fixture(scope="module")
def two_rank_runs(tmp_path_factory, tiny_scene_dir):
    """One torchrun launch: each method at 2 ranks x 1 view, then a run in which rank 1 drifts."""
    root = tmp_path_factory.mktemp("dist")
    entries = [{"name": m, "argv": method_argv(m, root / "runs" / m)} for m in METHODS]
    # after the densification window (which ends at step 10), before the checkpoint at 15
    entries.append({"name": "drift", "argv": tiny_argv("exploregs-default", root / "runs" / "drift"),
                    "diverge_at": 11})
    result = torchrun(root / "out", entries)
    assert result.returncode == 0, result.stderr[:6000]
    return root


@pytest.fixture(scope="module")
def one_process_runs(tmp_path_factory):
    """``run(method)``: the method's tiny run in one process with 2 views a step (the trainer and its
    metrics), trained once for every test that compares ranks with it."""
    root, runs = tmp_path_factory.mktemp("one-process"), {}

    def run(method: str):
        if method not in runs:
            trainer = parse_config(method_argv(method, root / method, "--batch-size", "2")).setup()
            runs[method] = (trainer, trainer.train())
        return runs[method]

    return run


def load_rank(root: Path, name: str, rank: int) -> dict:
    return torch.load(root / "out" / name / f"rank{rank}.pt")


# ----------------------------------------------------------------------------- one process
def test_schedule_counts_images_seen():
    config = ScheduleConfig()
    one = config.resolve(1200)
    four = config.resolve(300, views_per_step=4)
    assert one.views_per_step == 1 and four.views_per_step == 4
    # every event after the same number of images: steps x 4 at B = 4 equal the steps at B = 1
    assert four.refine_every * 4 == one.refine_every and four.reset_every * 4 == one.reset_every
    assert four.refine_start * 4 == one.refine_start and four.refine_stop * 4 == one.refine_stop
    assert four.sh_degree_interval * 4 == pytest.approx(one.sh_degree_interval, abs=2)
    # a schedule for B = 1 is the one the code always resolved
    assert one == ScheduleConfig().resolve(1200, 1)
    with pytest.raises(ValueError, match="views_per_step"):
        config.resolve(100, views_per_step=0)


def test_batch_rule_scales_learning_rates_and_betas(tiny_dm):
    params = torch.nn.ParameterDict({"means": torch.nn.Parameter(torch.zeros(3, 3))})
    opt = OptimizerConfig()
    one = opt.setup(params, 2.0)["means"].param_groups[0]
    four = opt.setup(params, 2.0, batch_size=4)["means"].param_groups[0]
    off = opt.setup(params, 2.0, batch_size=4, batch_rule=False)["means"].param_groups[0]
    assert four["lr"] == pytest.approx(2.0 * one["lr"]) and off["lr"] == one["lr"]
    assert four["betas"] == pytest.approx((0.9 ** 4, 0.999 ** 4)) and off["betas"] == one["betas"] == (0.9, 0.999)
    assert batch_betas(1) == (0.9, 0.999)


def test_paper_budget_splits_per_image_seen_and_batch_must_divide_among_ranks():
    assert resolve_budget("paper", 10, 100, 10).n_split == 20
    assert resolve_budget("paper", 10, 100, 10, views_per_step=4).n_split == 80
    # a scaled budget fixes totals over the window, so a shorter window in steps splits more per step
    b1 = resolve_budget("cpu-small", 16, 500, 100)
    b4 = resolve_budget("cpu-small", 4, 125, 25, views_per_step=4)
    assert b4.n_split * (121 // b4.split_every) == pytest.approx(b1.n_split * (484 // b1.split_every), rel=0.1)
    assert resolve_batch_size(None, 4) == 4 and resolve_batch_size(8, 4) == 8 and resolve_batch_size(None) == 1
    with pytest.raises(ValueError, match="cannot be shared by 2 ranks"):
        resolve_batch_size(3, 2)
    with pytest.raises(ValueError, match=">= 1"):
        resolve_batch_size(0)


def test_batched_statistics_count_views_not_steps(tiny_scene_dir):
    """One step of 2 views adds, per Gaussian, the same NDC statistic and view count as the two
    views rendered one by one from the same parameters (the 1/B of the mean loss is undone)."""

    def pipeline(batch: int):
        config = replace(get_method("exploregs-default").config, data="builtin:tiny")
        model = replace(config.pipeline.model, raster=RasterSettings(workers=1))
        return replace(config.pipeline, batch_size=batch, model=model).setup(config.schedule.resolve(100, batch), 0)

    indices = pipeline(2).datamanager.next_train_indices(2)  # the views the batched step will draw
    two = pipeline(2)
    two.train_step(0)
    stats2 = two.strategy_state["stats"]

    one = pipeline(1)
    expected: dict = {}
    for index in indices:
        camera, target, _ = one.datamanager.train_item(index)
        image, _, _, info = one.model.render(camera, 0, one.background)
        info["means2d"].retain_grad()
        photometric_loss(image, target, one.config.ssim_lambda)[0].backward()
        view = observe_render(info)
        accumulate_grad_stats(expected, view.screen_gradient().unsqueeze(0), view.visible().unsqueeze(0),
                              view.width, view.height)
    expected_grad, expected_count = expected["grad2d"], expected["count"]
    assert torch.equal(stats2["count"], expected_count) and expected_count.max() == 2
    torch.testing.assert_close(stats2["grad2d"], expected_grad, rtol=1e-5, atol=1e-9)


def test_single_process_world_is_free_and_launch_helpers():
    world = World()
    assert world.is_main and not world.is_distributed
    t = torch.ones(3)
    world.all_reduce_sum_([t])
    assert torch.equal(t, torch.ones(3)) and world.all_gather_object(5) == [5] and world.any_of(True, False) == (True, False)
    world.check_same("x", params_checksum([t]))  # nothing to compare with: no error
    assert not launched_by_torchrun({}) and launched_by_torchrun({"RANK": "0", "WORLD_SIZE": "2"})
    assert ranks_threads(2, cpus=16) == 8 and ranks_threads(4, cpus=2) == 1
    assert 0 < free_port() < 65536
    with pytest.raises(ValueError, match="master-port"):
        MachineConfig(num_machines=2)
    with pytest.raises(ValueError, match="machine-rank"):
        MachineConfig(num_machines=2, machine_rank=2, master_port=1234)


# ----------------------------------------------------------------------------- several processes
@pytest.mark.parametrize("method", METHODS)
def test_two_ranks_equal_one_process_with_two_views(two_rank_runs, one_process_runs, method):
    trainer, _ = one_process_runs(method)
    reference = {k: v.detach() for k, v in trainer.pipeline.params.items()}
    ranks = load_rank(two_rank_runs, method, 0)
    assert ranks["num_gaussians"] == trainer.pipeline.model.num_gaussians
    assert_close(ranks["params"], reference)
    # the run densified at least twice and reset the opacities, or added and relocated Gaussians
    # (and the counts agree)
    events = {"exploregs-mcmc": ("added", "relocated")}.get(method, ("cloned", "opacity_reset"))
    assert ranks["counts"] == trainer.op_totals and all(ranks["counts"].get(e, 0) > 0 for e in events)
    assert trainer.schedule.refine_every * 2 < trainer.schedule.refine_stop - trainer.schedule.refine_start


@pytest.mark.parametrize("method", METHODS)
def test_all_ranks_hold_identical_parameters(two_rank_runs, method):
    zero, one = load_rank(two_rank_runs, method, 0), load_rank(two_rank_runs, method, 1)
    assert zero["num_gaussians"] == one["num_gaussians"]
    assert all(torch.equal(zero["params"][k], one["params"][k]) for k in zero["params"])


def test_rank_that_drifts_stops_the_run_at_the_next_checkpoint(two_rank_runs):
    folder = two_rank_runs / "out" / "drift"
    errors = [(folder / f"rank{r}.error").read_text() for r in (0, 1)]
    assert all("rank(s) [1] differ from rank 0" in e and "step 15" in e for e in errors)
    # the drifted state never reached a checkpoint
    run = two_rank_runs / "runs" / "drift"
    assert [p.name for p in list_checkpoints(run)] == ["step-0000005.pt", "step-0000010.pt"]


def test_two_rank_checkpoint_resumes_in_one_process(two_rank_runs, tmp_path):
    source = two_rank_runs / "runs" / "exploregs-seedsplit"
    copy = tmp_path / "resumed"
    (copy / "checkpoints").mkdir(parents=True)
    shutil.copy(source / "config.yml", copy / "config.yml")
    # before two densifications and the opacity reset: the resumed run does them
    shutil.copy(source / "checkpoints" / "step-0000005.pt", copy / "checkpoints")
    trainer = Trainer.from_run(copy, num_devices=1)
    assert trainer.world.size == 1 and trainer.pipeline.batch_size == 2 and trainer.start_step == 5
    trainer.train()
    assert_close({k: v.detach() for k, v in trainer.pipeline.params.items()},
                 load_rank(two_rank_runs, "exploregs-seedsplit", 0)["params"])


def test_two_machines_on_loopback_train_together(tmp_path, tiny_scene_dir, one_process_runs):
    port = free_port()
    run_dir = tmp_path / "run"
    argv = tiny_argv("exploregs-default", run_dir, "--machine.num-machines", "2", "--machine.master-port", str(port),
                     "--tensorboard")
    procs = [subprocess.Popen([sys.executable, "-m", "exploregs_plugin.scripts.train", *argv,
                               "--machine.machine-rank", str(rank)], env=worker_env(), stderr=subprocess.PIPE,
                              text=True) for rank in (0, 1)]
    try:
        errs = [p.communicate(timeout=180)[1] for p in procs]
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
    assert [p.returncode for p in procs] == [0, 0], errs
    metrics = json.loads((run_dir / "metrics.json").read_text())
    assert len(list(run_dir.glob("events.out.tfevents.*"))) == 1  # rank 0 alone logs
    assert metrics["world_size"] == 2 and metrics["batch_size"] == 2 and metrics["images_seen"] == 2 * STEPS
    _, reference = one_process_runs("exploregs-default")
    assert metrics["num_gaussians"] == reference["num_gaussians"]
    assert metrics["psnr"] == pytest.approx(reference["psnr"], abs=1e-4)


def _rank_pid(parent: int, rank: int) -> int | None:
    """The pid of the worker process of ``rank`` among the children of ``parent`` (Linux /proc)."""
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            ppid = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
            environ = (entry / "environ").read_bytes().split(b"\0")
        except (OSError, IndexError, ValueError):
            continue
        if ppid == parent and f"RANK={rank}".encode() in environ:
            return int(entry.name)
    return None


@pytest.mark.skipif(not Path("/proc/self/environ").exists(), reason="finds the rank's process through /proc")
def test_killed_rank_ends_the_job_with_a_clear_error(tmp_path, tiny_scene_dir):
    run_dir = tmp_path / "run"
    argv = [*tiny_argv("exploregs-seedsplit", run_dir, "--machine.num-devices", "2", steps=100_000),
            "--checkpoint-every", "5"]
    proc = subprocess.Popen([sys.executable, "-m", "exploregs_plugin.scripts.train", *argv], env=worker_env(),
                            stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        deadline = time.monotonic() + 120
        while len(list_checkpoints(run_dir)) < 2 and time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.2)
        assert len(list_checkpoints(run_dir)) >= 2, "the run never wrote a checkpoint"
        pid = _rank_pid(proc.pid, 1)
        assert pid is not None
        os.kill(pid, signal.SIGKILL)
        killed = time.monotonic()
        _, err = proc.communicate(timeout=60)
        ended_after = time.monotonic() - killed
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 1 and ended_after < 30, err[-2000:]
    assert f"rank 1 (pid {pid}) failed with SIGKILL; the other ranks were stopped" in err
    good = load_checkpoint(latest_checkpoint(run_dir))  # the newest checkpoint is whole
    assert good["step"] > 0 and all(torch.isfinite(v).all() for v in good["params"].values())
    # a short message: what was launched, where the run is, which rank was lost and how to go on
    lines = err.strip().splitlines()
    assert lines[0] == "launched 2 ranks" and f"run folder: {run_dir}" in lines and "Traceback" not in err
    assert all(ln.startswith(QUIET_START) for ln in lines[:-1]), err[-3000:]
    assert lines[-1] == (f"eg-train: error: rank 1 (pid {pid}) failed with SIGKILL; the other ranks were stopped; "
                         f"continue with: eg-train --resume {run_dir}")


QUIET_START = ("launched ", "run folder: ", "renderer: ", "building ")
"""What a launched job prints before its one last line: the ranks, the run folder, the renderer."""


def _launch(run_dir: Path, *extra: str) -> subprocess.Popen:
    """A long 2-rank job through eg-train's own launcher, in its own session (as in a terminal).
    The torch renderer: these tests are about signals, not about waiting for a compiled one."""
    argv = [*tiny_argv("exploregs-default", run_dir, "--machine.num-devices", "2", steps=100_000),
            "--model.raster.backend", "torch", *extra]
    return subprocess.Popen([sys.executable, "-m", "exploregs_plugin.scripts.train", *argv], env=worker_env(),
                            stderr=subprocess.PIPE, text=True, start_new_session=True)


def _end(proc: subprocess.Popen) -> None:
    """Kill what a failed test left: the launcher's group and its ranks (each in its own session)."""
    ranks = [pid for pid in (_rank_pid(proc.pid, rank) for rank in (0, 1)) if pid is not None]
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    for pid in ranks:
        if _alive(pid):
            os.kill(pid, signal.SIGKILL)


def _wait_for(condition, proc: subprocess.Popen, seconds: float = 120) -> None:
    deadline = time.monotonic() + seconds
    while not condition() and time.monotonic() < deadline and proc.poll() is None:
        time.sleep(0.1)
    assert condition(), "the job never got there"


def _alive(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


@pytest.mark.skipif(not Path("/proc/self/environ").exists(), reason="finds the ranks through /proc")
@pytest.mark.parametrize("signum", [signal.SIGINT, pytest.param(signal.SIGTERM, marks=pytest.mark.slow)])
def test_ctrl_c_or_sigterm_stops_a_launched_job_with_one_line(tmp_path, tiny_scene_dir, signum,
                                                             sigint_as_in_a_terminal):
    run_dir = tmp_path / "run"
    proc = _launch(run_dir, "--checkpoint-every", "2")
    try:
        _wait_for(lambda: list_checkpoints(run_dir), proc)
        proc.send_signal(signum)  # what Ctrl-C in the terminal sends the launcher (the ranks have their own session)
        _, err = proc.communicate(timeout=90)
    finally:
        _end(proc)
    name = signal.Signals(signum).name
    assert proc.returncode == 128 + signum, err[-3000:]
    lines = err.strip().splitlines()
    assert lines[0] == "launched 2 ranks" and f"run folder: {run_dir}" in lines and "Traceback" not in err
    # one stop line (rank 0's), nothing from the other rank or torch's launcher
    assert all(ln.startswith(QUIET_START) for ln in lines[:-1]), err[-3000:]
    step = load_checkpoint(latest_checkpoint(run_dir))["step"]
    assert lines[-1] == (f"eg-train: error: stopped by {name} after step {step}, saved in "
                         f"{latest_checkpoint(run_dir)}; resume with: eg-train --resume {run_dir}")


def test_repeated_launcher_signals_are_one_stop_request_but_a_second_sigterm_stops_at_once(monkeypatch):
    """The kernel sends a rank one parent-death signal per thread of its dying launcher: the
    repeats must not stop the rank at once (the other rank would wait in a collective forever),
    and after the loop they are ignored; a SIGTERM after them still means "stop now"."""
    from exploregs_plugin.runtime.distributed import LAUNCHER_GONE, LAUNCHER_PID
    from exploregs_plugin.engine.stopping import Stopped, StopOnSignals

    monkeypatch.setenv(LAUNCHER_PID, "1")
    before = signal.getsignal(LAUNCHER_GONE)
    with StopOnSignals() as stop:
        assert signal.getsignal(LAUNCHER_GONE) == stop._handler
        for _ in range(3):
            stop._handler(LAUNCHER_GONE, None)
        assert stop.requested and stop.signum == LAUNCHER_GONE
        with pytest.raises(Stopped, match="stopped by SIGTERM at once"):  # someone insists
            stop._handler(signal.SIGTERM, None)
    assert signal.getsignal(LAUNCHER_GONE) == signal.SIG_IGN  # late repeats while leaving the group
    signal.signal(LAUNCHER_GONE, before)


@pytest.mark.skipif(not Path("/proc/self/environ").exists(), reason="finds the ranks through /proc")
def test_ranks_stop_when_their_launcher_is_killed(tmp_path, tiny_scene_dir):
    run_dir = tmp_path / "run"
    proc = _launch(run_dir, "--checkpoint-every", "2")
    ranks: list[int | None] = []
    try:
        _wait_for(lambda: list_checkpoints(run_dir), proc)
        ranks = [_rank_pid(proc.pid, rank) for rank in (0, 1)]
        assert None not in ranks
        proc.kill()  # kill -9: the launcher can pass nothing on
        proc.wait(timeout=30)
        deadline = time.monotonic() + 120  # a step, the agreement, a checkpoint, leaving the group: slow on a busy machine
        while any(_alive(pid) for pid in ranks) and time.monotonic() < deadline:
            time.sleep(0.2)
        orphans = [pid for pid in ranks if _alive(pid)]
    finally:
        for pid in ranks:
            if pid is not None and _alive(pid):
                os.kill(pid, signal.SIGKILL)
        _end(proc)
    assert not orphans, "ranks went on training without their launcher"
    err = proc.stderr.read()
    # the kernel sends the parent-death signal once per thread of the dying launcher: the ranks
    # take the repeats as one request, agree on a step and checkpoint there (rank 0 says where)
    step = load_checkpoint(latest_checkpoint(run_dir))["step"]
    assert err.strip().splitlines()[-1] == (
        f"eg-train: error: stopped by SIGHUP (its launcher is gone) after step {step}, saved in "
        f"{latest_checkpoint(run_dir)}; resume with: eg-train --resume {run_dir}"), err[-3000:]
    assert "Traceback" not in err
    good = load_checkpoint(latest_checkpoint(run_dir))  # they checkpointed on the way out
    assert all(torch.isfinite(v).all() for v in good["params"].values())


@pytest.mark.skipif(not Path("/proc/self/environ").exists(), reason="finds the rank's process through /proc")
def test_a_rank_lost_before_any_checkpoint_says_to_start_again(tmp_path, tiny_scene_dir):
    run_dir = tmp_path / "run"
    proc = _launch(run_dir, "--checkpoint-every", "100000", "--checkpoint-minutes", "0")
    try:
        _wait_for(lambda: (run_dir / "config.yml").is_file() and _rank_pid(proc.pid, 1) is not None, proc)
        pid = _rank_pid(proc.pid, 1)
        os.kill(pid, signal.SIGKILL)
        _, err = proc.communicate(timeout=60)
    finally:
        _end(proc)
    assert proc.returncode == 1
    assert err.strip().splitlines()[-1] == (
        f"eg-train: error: rank 1 (pid {pid}) failed with SIGKILL; the other ranks were stopped; no checkpoint "
        f"was written yet: start the run again ({run_dir / 'config.yml'} holds its settings)")
    assert "--resume" not in err and not list_checkpoints(run_dir)


def test_resume_options_take_device_and_ranks(capsys):
    from exploregs_plugin.scripts.train import resume_options

    assert resume_options(["--resume", "RUN"]) == (Path("RUN"), None, None)
    assert resume_options(["--resume", "RUN", "--machine.num-devices", "1", "--device", "cpu"]) == (Path("RUN"), "cpu", 1)
    for bad in (["--resume"], ["--resume", "RUN", "--device"], ["--resume", "RUN", "--max-steps", "5"],
                ["--resume", "RUN", "--machine.num-devices", "0"]):
        with pytest.raises(SystemExit):
            resume_options(bad)
    assert "--machine.num-devices" in capsys.readouterr().err


def test_a_batch_the_ranks_cannot_share_is_refused_before_any_rank_starts(tmp_path):
    from exploregs_plugin.scripts.train import main

    argv = tiny_argv("exploregs-default", tmp_path / "run", "--batch-size", "3", "--machine.num-devices", "2")
    with pytest.raises(ValueError, match="--batch-size 3 cannot be shared by 2 ranks"):
        main(argv)
    assert not (tmp_path / "run").exists()
