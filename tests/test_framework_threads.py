"""Every command waits passively in OpenMP and uses one thread per CPU it may run on."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from exploregs_plugin.runtime.threads import available_cpus, default_threads

# What a console entry point does (the eg-train script imports its module first, then run_cli),
# then what the OpenMP runtime and torch ended up with. OMP_DISPLAY_ENV makes each libgomp print
# the settings it read when it was loaded: GOMP_SPINCOUNT 0 is passive waiting as the runtime
# applies it. (torch's own libgomp loads with torch: importing torch before the package would
# leave it spinning, and a second libgomp that loads later, pycolmap's, would hide that.)
PROBE_IMPORTS = """
from exploregs_plugin.scripts.train import main
from exploregs_plugin.scripts import run_cli
import os, torch
"""
PROBE_COMMAND = """
run_cli("probe", lambda _: print("threads", torch.get_num_threads(), os.environ.get("OMP_WAIT_POLICY")), None)
"""
PROBE = PROBE_IMPORTS + PROBE_COMMAND
PROBE_TWICE_ON_CUE = PROBE + """
import sys
print("imported", flush=True)
sys.stdin.readline()
""" + PROBE_COMMAND
"""The probe, then its command again on a line on stdin: a competitor started then has to keep its
CPU busy only while the second command measures, not through the seconds of importing torch (the
first command is a command without a competitor, in the same process: one torch import less)."""


def probe_environ(**env: str) -> dict[str, str]:
    environ = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "OMP_NUM_THREADS")}
    environ.update(env, OMP_DISPLAY_ENV="VERBOSE")
    return environ


def probe(cpus: set[int] | None = None, **env: str) -> tuple[str, str]:
    preexec = (lambda: os.sched_setaffinity(0, cpus)) if cpus else None
    out = subprocess.run([sys.executable, "-c", PROBE], env=probe_environ(**env), capture_output=True, text=True,
                         timeout=120, preexec_fn=preexec)
    assert out.returncode == 0, out.stderr[-2000:]
    return out.stdout.strip().splitlines()[-1], out.stderr


@pytest.mark.skipif(not hasattr(os, "sched_setaffinity"), reason="needs CPU affinity (Linux)")
def test_commands_wait_passively_with_one_thread_per_allowed_cpu():
    one = {sorted(os.sched_getaffinity(0))[0]}
    line, runtime = probe(one)
    assert line == "threads 1 PASSIVE"
    spin = [ln.strip() for ln in runtime.splitlines() if "GOMP_SPINCOUNT" in ln]
    assert spin and set(spin) == {"GOMP_SPINCOUNT = '0'"}, spin  # set before torch loaded its runtime
    # every CPU allowed: the test below runs the command on two CPUs before a competitor comes (on a
    # machine of one CPU the probe above is that command)


def ended(proc: subprocess.Popen) -> str:
    """The end of the stderr of a probe that went wrong, killed first: one that waits for its cue
    would never close it."""
    proc.kill()
    return proc.stderr.read()[-2000:]


@pytest.mark.skipif(not hasattr(os, "sched_setaffinity") or len(os.sched_getaffinity(0)) < 2,
                    reason="needs two CPUs and CPU affinity (Linux)")
def test_a_busy_process_on_one_of_two_cpus_leaves_one_thread():
    a, b = sorted(os.sched_getaffinity(0))[:2]
    command = subprocess.Popen([sys.executable, "-c", PROBE_TWICE_ON_CUE], env=probe_environ(),
                               stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                               preexec_fn=lambda: os.sched_setaffinity(0, {a, b}))
    busy = None
    try:
        # before the competitor, every CPU the command may use is allowed a thread: passive, at most
        # a thread per CPU (fewer while other processes keep some busy)
        first = command.stdout.readline().strip()
        assert first.startswith("threads ") and first.endswith(" PASSIVE"), (first, ended(command))
        assert 1 <= int(first.split()[1]) <= 2, first
        assert command.stdout.readline().strip() == "imported", ended(command)
        busy = subprocess.Popen([sys.executable, "-c", "print('spinning', flush=True)\nwhile True: pass"],
                                stdout=subprocess.PIPE, text=True, preexec_fn=lambda: os.sched_setaffinity(0, {a}))
        assert busy.stdout.readline().strip() == "spinning"
        command.stdin.write("go\n")
        command.stdin.flush()
        line = command.stdout.readline().strip()
        busy.kill()  # the command has measured: no need to spin while it exits
        out, err = command.communicate(timeout=120)
    finally:
        for proc in (busy, command):
            if proc is not None:
                proc.kill()
                proc.wait()
    assert command.returncode == 0, err[-2000:]
    assert line == "threads 1 PASSIVE"


def test_idle_cpus_subtract_other_processes_but_not_this_one(tmp_path, monkeypatch):
    from exploregs_plugin.runtime.threads import IdleCpus, threads_for

    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1}, raising=False)
    (tmp_path / "self").mkdir()

    def write(busy0: int, idle0: int, busy1: int, idle1: int, own: int) -> None:
        # /proc/stat: cpuN user nice system idle iowait irq softirq steal ...; /proc/self/stat: utime stime
        (tmp_path / "stat").write_text(f"cpu  0 0 0 0 0 0 0 0 0 0\ncpu0 {busy0} 0 0 {idle0} 0 0 0 0 0 0\n"
                                       f"cpu1 {busy1} 0 0 {idle1} 0 0 0 0 0 0\ncpu2 999 0 0 0 0 0 0 0 0 0\n")
        (tmp_path / "self" / "stat").write_text(f"42 (python) R 1 1 1 0 -1 0 0 0 0 0 {own} 0 0 0 20\n")

    write(0, 0, 0, 0, 0)
    watch = IdleCpus(tmp_path)
    write(100, 0, 0, 100, 0)  # another process kept cpu0 busy, cpu1 idle: one CPU left
    assert watch.sample() == pytest.approx(1.0) and threads_for(1.0, 2) == 1
    write(200, 0, 100, 100, 200)  # both busy with this process's own work: two CPUs left
    assert watch.sample() == pytest.approx(2.0) and threads_for(2.0, 2) == 2
    write(200, 0, 100, 100, 200)  # no time passed: unknown, so every CPU
    assert watch.sample() is None and threads_for(None, 2) == 2


def test_a_cpu_gets_a_thread_only_when_three_quarters_of_it_is_idle():
    from exploregs_plugin.runtime.threads import threads_for

    # a CPU half taken by another process gets no thread: a second thread with half a core makes
    # every equally split parallel region as slow as one thread, plus the waits at its end
    assert [threads_for(idle, 2) for idle in (0.0, 0.7, 1.0, 1.5, 1.74, 1.75, 2.0)] == [1, 1, 1, 1, 1, 2, 2]
    assert [threads_for(idle, 4) for idle in (3.6, 3.75, 2.5, 0.1)] == [3, 4, 2, 1]
    assert threads_for(None, 4) == 4  # unknown: every CPU

    def settle(cpus: int, busy: int) -> int:
        # ``busy`` processes keep a CPU busy each; with n threads of ours beside them on ``cpus``
        # CPUs the scheduler's fair shares leave cpus - busy cpus / (n + busy) idle as measured
        # (cpus - busy while there are enough CPUs); the run starts at every CPU and re-checks
        n = cpus
        for _ in range(cpus + 2):
            n = threads_for(cpus - busy if n + busy <= cpus else cpus - busy * cpus / (n + busy), cpus)
        return n

    # one thread beside one or two busy processes on two CPUs (the issue-48 setting); one per free CPU on four
    assert [settle(2, busy) for busy in (0, 1, 2)] == [2, 1, 1]
    assert [settle(4, busy) for busy in (0, 1, 2, 3, 4)] == [4, 3, 2, 1, 1]
    for cpus in (2, 3, 4, 8, 16, 64):  # where it settles no thread of ours has less than 3/4 of a core
        for busy in range(2 * cpus + 2):
            n = settle(cpus, busy)
            assert n == 1 or n + busy <= cpus or cpus / (n + busy) >= 0.75, (cpus, busy, n)


def test_the_thread_bench_tables_medians_threads_and_the_ratio():
    from exploregs_plugin.bench.components.threads import table

    rows = [{"competitors": 0, "setting": "default", "seconds": 10.0, "threads": [2]},
            {"competitors": 0, "setting": "one thread", "seconds": 12.0, "threads": [1]},
            {"competitors": 1, "setting": "default", "seconds": 13.0, "threads": [1]},
            {"competitors": 1, "setting": "default", "seconds": 15.0, "threads": [1, 2]},
            {"competitors": 1, "setting": "one thread", "seconds": 12.0, "threads": [1]}]
    assert table(rows).splitlines()[2:] == ["| 0 | 10.00 (10.00-10.00) | [2] | 12.00 (12.00-12.00) | 0.83 |",
                                            "| 1 | 14.00 (13.00-15.00) | [1, 2] | 12.00 (12.00-12.00) | 1.17 |"]


def test_a_wait_policy_or_thread_count_the_user_set_is_kept():
    line, runtime = probe(OMP_WAIT_POLICY="ACTIVE", OMP_NUM_THREADS="1")
    assert line == "threads 1 ACTIVE" and "GOMP_SPINCOUNT = '0'" not in runtime


def test_default_threads_follow_affinity_and_omp_num_threads(monkeypatch):
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    assert 1 <= default_threads() <= available_cpus()
    if hasattr(os, "sched_getaffinity"):
        assert available_cpus() == len(os.sched_getaffinity(0))
    monkeypatch.setenv("OMP_NUM_THREADS", "3")
    assert default_threads() == 3
    monkeypatch.setenv("OMP_NUM_THREADS", "many")  # not a count: ignored
    assert 1 <= default_threads() <= available_cpus()


def test_a_run_follows_the_idle_cpus_between_steps_and_restores_the_count(tmp_path, tiny_scene_dir, monkeypatch):
    import torch

    from exploregs_plugin.engine import thread_follower
    from exploregs_plugin.engine import trainer as trainer_module
    from exploregs_plugin.callbacks import TrainingCallback
    from exploregs_plugin.runtime.threads import IdleCpus

    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    monkeypatch.setattr(thread_follower, "THREADS_CHECK_SECONDS", 0.0)
    monkeypatch.setattr(thread_follower, "FIRST_THREADS_CHECK_SECONDS", 0.0)
    monkeypatch.setattr(thread_follower, "available_cpus", lambda: 2)
    idle = iter([2.0, 2.0, 1.0, 1.0, 2.0, 2.0])  # a competitor comes and goes
    monkeypatch.setattr(IdleCpus, "sample", lambda self: next(idle, 2.0))
    seen: list[int] = []

    class Threads(TrainingCallback):
        def after_step(self, trainer, step, stats):
            seen.append(torch.get_num_threads())

    before = torch.get_num_threads()
    config = trainer_module.TrainerConfig(data="builtin:tiny", max_steps=6, run_dir=tmp_path / "run", quiet=True,
                                          tensorboard=False, eval_count=1, save_eval_images=False, device="cpu")
    metrics = trainer_module.Trainer(config, callbacks=[Threads()]).train()
    assert seen == [2, 2, 1, 1, 2, 2] and torch.get_num_threads() == before
    assert metrics["threads"] == sorted({before, 1, 2})


def test_a_run_checks_the_idle_cpus_soon_after_it_starts(tmp_path, tiny_scene_dir, monkeypatch):
    # the count a run starts with was measured when the command started, before its data loaded:
    # the first check comes after FIRST_THREADS_CHECK_SECONDS of training, the next ones every
    # THREADS_CHECK_SECONDS
    import torch

    from exploregs_plugin.engine import thread_follower
    from exploregs_plugin.engine import trainer as trainer_module
    from exploregs_plugin.callbacks import TrainingCallback
    from exploregs_plugin.runtime.threads import IdleCpus

    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    monkeypatch.setattr(thread_follower, "THREADS_CHECK_SECONDS", 1e6)
    monkeypatch.setattr(thread_follower, "FIRST_THREADS_CHECK_SECONDS", 0.0)
    monkeypatch.setattr(thread_follower, "available_cpus", lambda: 2)
    idle = iter([1.0, 2.0])  # a competitor came while the data loaded (then left: too late to be seen)
    monkeypatch.setattr(IdleCpus, "sample", lambda self: next(idle))
    seen: list[int] = []

    class Threads(TrainingCallback):
        def after_step(self, trainer, step, stats):
            seen.append(torch.get_num_threads())

    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        config = trainer_module.TrainerConfig(data="builtin:tiny", max_steps=3, run_dir=tmp_path / "run", quiet=True,
                                              tensorboard=False, eval_count=1, save_eval_images=False, device="cpu")
        trainer_module.Trainer(config, callbacks=[Threads()]).train()
    finally:
        torch.set_num_threads(before)
    assert seen == [1, 1, 1]


def test_num_threads_overrides_the_default(tmp_path, tiny_scene_dir):
    import torch

    from exploregs_plugin.engine.trainer import TrainerConfig

    before = torch.get_num_threads()
    try:
        TrainerConfig(data="builtin:tiny", max_steps=1, run_dir=tmp_path / "run", quiet=True, num_threads=1).setup()
        assert torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(before)
