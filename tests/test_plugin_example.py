"""The plug-in API: a separately pip-installed package adds a strategy and a method."""

from __future__ import annotations

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
def installed_plugin():
    out = _pip("install", "--no-deps", "--no-build-isolation", "--quiet", str(EXAMPLE))
    if out.returncode != 0:
        pytest.fail(f"pip install of the example plugin failed:\n{out.stderr}")
    yield
    _pip("uninstall", "--yes", "--quiet", "exploregs-plugin-example")


def test_plugin_method_and_strategy_are_found_and_train(installed_plugin, tmp_path, tiny_scene_dir):
    train = [sys.executable, "-m", "exploregs_plugin.scripts.train"]
    wide = {**os.environ, "COLUMNS": "250"}  # keep each description on one line
    listing = subprocess.run(train + ["--help"], capture_output=True, text=True, timeout=120, env=wide)
    assert listing.returncode == 0 and "example-opacity-budget" in listing.stdout
    assert "hard budget of Gaussians" in listing.stdout

    probe = subprocess.run(
        [sys.executable, "-c",
         "from exploregs_plugin.strategies import available_strategies as a; print(a()['opacity-budget'].__name__)"],
        capture_output=True, text=True, timeout=120)
    assert probe.stdout.strip() == "OpacityBudgetStrategy", probe.stderr

    run_dir = tmp_path / "run"
    result = subprocess.run(
        train + ["example-opacity-budget", "--data", "builtin:tiny", "--max-steps", "12",
                 "--strategy.limit.max-gaussians", "150", "--run-dir", str(run_dir), "--quiet", "--no-tensorboard",
                 "--eval-count", "1", "--no-save-eval-images"],
        capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]
    metrics = json.loads((run_dir / "metrics.json").read_text())
    assert metrics["method"] == "example-opacity-budget"
    assert 0 < metrics["num_gaussians"] <= 150

    # the plugin's operator composed after Seed+Split's two, picked by name for a built-in method
    run_dir = tmp_path / "seedsplit"
    result = subprocess.run(
        train + ["exploregs-seedsplit", "--strategy", "seedsplit-budget", "--strategy.limit.max-gaussians", "150",
                 "--strategy.splitting.n-split", "4", "--strategy.splitting.every", "1", "--data", "builtin:tiny",
                 "--max-steps", "12", "--run-dir", str(run_dir), "--quiet", "--no-tensorboard", "--eval-count", "1",
                 "--no-save-eval-images"],
        capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]
    metrics = json.loads((run_dir / "metrics.json").read_text())
    counts = metrics["strategy_counts"]
    assert counts["random_split"] > 0 and counts["budget_pruned"] > 0 and "seeded" in counts
    assert 0 < metrics["num_gaussians"] <= 150
