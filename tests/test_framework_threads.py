"""Every command waits passively in OpenMP and uses one thread per CPU it may run on."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from exploregs_plugin.threads import available_cpus, default_threads

# What a console entry point does first (import its module, then run_cli), then what the OpenMP
# runtime and torch ended up with. OMP_DISPLAY_ENV makes libgomp print the settings it read when
# torch loaded it: GOMP_SPINCOUNT 0 is passive waiting as the runtime applies it.
PROBE = """
import os, torch
from exploregs_plugin.scripts import run_cli
from exploregs_plugin.scripts.train import main
run_cli("probe", lambda _: print("threads", torch.get_num_threads(), os.environ.get("OMP_WAIT_POLICY")), None)
"""


def probe(cpus: set[int] | None = None, **env: str) -> tuple[str, str]:
    environ = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "OMP_NUM_THREADS")}
    environ.update(env, OMP_DISPLAY_ENV="VERBOSE")
    preexec = (lambda: os.sched_setaffinity(0, cpus)) if cpus else None
    out = subprocess.run([sys.executable, "-c", PROBE], env=environ, capture_output=True, text=True, timeout=120,
                         preexec_fn=preexec)
    assert out.returncode == 0, out.stderr[-2000:]
    return out.stdout.strip().splitlines()[-1], out.stderr


@pytest.mark.skipif(not hasattr(os, "sched_setaffinity"), reason="needs CPU affinity (Linux)")
def test_commands_wait_passively_with_one_thread_per_allowed_cpu():
    one = {sorted(os.sched_getaffinity(0))[0]}
    line, runtime = probe(one)
    assert line == "threads 1 PASSIVE"
    assert "GOMP_SPINCOUNT = '0'" in runtime  # the runtime read the policy: it was set before torch loaded it
    # every CPU allowed: as many threads as CPUs
    line, _ = probe()
    assert line == f"threads {len(os.sched_getaffinity(0))} PASSIVE"


def test_a_wait_policy_or_thread_count_the_user_set_is_kept():
    line, runtime = probe(OMP_WAIT_POLICY="ACTIVE", OMP_NUM_THREADS="1")
    assert line == "threads 1 ACTIVE" and "GOMP_SPINCOUNT = '0'" not in runtime


def test_default_threads_follow_affinity_and_omp_num_threads(monkeypatch):
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    assert default_threads() == available_cpus() >= 1
    if hasattr(os, "sched_getaffinity"):
        assert available_cpus() == len(os.sched_getaffinity(0))
    monkeypatch.setenv("OMP_NUM_THREADS", "3")
    assert default_threads() == 3
    monkeypatch.setenv("OMP_NUM_THREADS", "many")  # not a count: ignored
    assert default_threads() == available_cpus()


def test_num_threads_overrides_the_default(tmp_path, tiny_scene_dir):
    import torch

    from exploregs_plugin.trainer import TrainerConfig

    before = torch.get_num_threads()
    try:
        TrainerConfig(data="builtin:tiny", max_steps=1, run_dir=tmp_path / "run", quiet=True, num_threads=1).setup()
        assert torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(before)
