"""The plug-in API: a separately pip-installed package adds a strategy and a method."""

from __future__ import annotations

import importlib
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "plugin_example"


def _pip(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "pip", "--disable-pip-version-check", *args],
                          capture_output=True, text=True, timeout=600)


@pytest.fixture(scope="module")
def installed_plugin(tmp_path_factory):
    """The example pip-installed into a folder of its own, on the import path of this process and
    of the commands it starts (PYTHONPATH): found through its entry points as in site-packages,
    with nothing to uninstall (a pip process less) and nothing changed in the environment, which
    other test runs may be using meanwhile."""
    target = tmp_path_factory.mktemp("plugin-site")
    out = _pip("install", "--no-deps", "--no-build-isolation", "--quiet", "--target", str(target), str(EXAMPLE))
    if out.returncode != 0:
        pytest.fail(f"pip install of the example plugin failed:\n{out.stderr}")
    with pytest.MonkeyPatch.context() as patch:
        patch.syspath_prepend(str(target))
        patch.setenv("PYTHONPATH", os.pathsep.join(filter(None, [str(target), os.environ.get("PYTHONPATH")])))
        yield


def test_plugin_method_and_strategy_are_found_and_train(installed_plugin, tmp_path, tiny_scene_dir, capsys,
                                                        monkeypatch, one_thread):
    from exploregs_plugin.scripts.train import parse_config
    from exploregs_plugin.strategies import available_strategies

    # The listing and the registry read the installed packages' entry points at each call, so this
    # process finds the plugin installed after it started as a new one does (the first run below
    # is a new eg-train process); the import system is told the site folder changed.
    importlib.invalidate_caches()
    monkeypatch.setenv("COLUMNS", "250")  # keep each description on one line
    with pytest.raises(SystemExit) as listing:
        parse_config(["--help"])
    out = capsys.readouterr().out
    assert listing.value.code in (0, None) and "example-opacity-budget" in out
    assert "hard budget of Gaussians" in out

    assert available_strategies()["opacity-budget"].__name__ == "OpacityBudgetStrategy"

    train = [sys.executable, "-m", "exploregs_plugin.scripts.train"]
    # a run of this size on one thread: a second only waits for the first (and spins while it
    # waits on a busy machine); the thread count changes no result
    one_thread_env = {**os.environ, "OMP_NUM_THREADS": "1"}
    # the plugin's method in a new eg-train process: what a user who pip-installed it runs
    run_dir = tmp_path / "run"
    result = subprocess.run(
        train + ["example-opacity-budget", "--data", "builtin:tiny", "--max-steps", "12",
                 "--strategy.limit.max-gaussians", "150", "--run-dir", str(run_dir), "--quiet", "--no-tensorboard",
                 "--eval-count", "1", "--no-save-eval-images"],
        capture_output=True, text=True, timeout=600, env=one_thread_env)
    assert result.returncode == 0, result.stderr[-3000:]
    metrics = json.loads((run_dir / "metrics.json").read_text())
    assert metrics["method"] == "example-opacity-budget"
    assert 0 < metrics["num_gaussians"] <= 150

    # the plugin's operator composed after Seed+Split's two, picked by name for a built-in method.
    # In this process (eg-train's own parsing, --strategy included, and training): that a new
    # process finds the plugin the run above showed, and a second one would cost a torch import
    run_dir = tmp_path / "seedsplit"
    parse_config(["exploregs-seedsplit", "--strategy", "seedsplit-budget", "--strategy.limit.max-gaussians", "150",
                  "--strategy.splitting.n-split", "4", "--strategy.splitting.every", "1", "--data", "builtin:tiny",
                  "--max-steps", "12", "--run-dir", str(run_dir), "--quiet", "--no-tensorboard", "--eval-count", "1",
                  "--no-save-eval-images", "--num-threads", "1"]).setup().train()  # one_thread restores it
    metrics = json.loads((run_dir / "metrics.json").read_text())
    counts = metrics["strategy_counts"]
    assert counts["random_split"] > 0 and counts["budget_pruned"] > 0 and "seeded" in counts
    assert 0 < metrics["num_gaussians"] <= 150
