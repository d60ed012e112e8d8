"""experiments/gpu/summary.py: simple_trainer's training clock rebuilt from its files, and the
time to a PSNR level read from a curve (the figures docs/gpu.md reports from a GPU run)."""

from __future__ import annotations

import importlib.util
import json
import os
from pathlib import Path

import pytest

SUMMARY = Path(__file__).resolve().parents[1] / "experiments" / "gpu" / "summary.py"


@pytest.fixture(scope="module")
def summary():
    spec = importlib.util.spec_from_file_location("gpu_summary", SUMMARY)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def write_simple_trainer_run(root: Path, evaluations: list[tuple[int, float, float, float]]) -> None:
    """simple_trainer's stats files as it writes them: at step K-1 ``train_step{K-1}_rank0.json``
    (``ellipse_time``: loop seconds so far, its earlier saves and evaluations included), then
    after its save and evaluation ``val_step{K-1}.json``; modification times as the clock had them.
    ``evaluations``: (step K, ellipse_time, seconds of save + evaluation, PSNR)."""
    stats = root / "stats"
    stats.mkdir(parents=True)
    start = 1_000_000.0
    for step, ellipse, overhead, psnr in evaluations:
        train = stats / f"train_step{step - 1:04d}_rank0.json"
        train.write_text(json.dumps({"mem": 0.5, "ellipse_time": ellipse, "num_GS": 100}))
        os.utime(train, (start + ellipse, start + ellipse))
        val = stats / f"val_step{step - 1:04d}.json"
        val.write_text(json.dumps({"psnr": psnr, "ssim": 0.9, "num_GS": 100}))
        os.utime(val, (start + ellipse + overhead, start + ellipse + overhead))


def test_simple_trainer_clock_leaves_out_its_saves_and_evaluations(summary, tmp_path):
    # training of 10 s between evaluations; the saves and evaluations take 3, 4 and 2 s, which
    # every later ellipse_time includes
    write_simple_trainer_run(tmp_path, [(1000, 10.0, 3.0, 20.0), (2000, 23.0, 4.0, 24.0), (3000, 37.0, 2.0, 25.0)])
    history = summary.simple_trainer_history(str(tmp_path))
    assert [p["step"] for p in history] == [1000, 2000, 3000]
    assert [p["train_seconds"] for p in history] == pytest.approx([10.0, 20.0, 30.0])
    assert [p["psnr"] for p in history] == [20.0, 24.0, 25.0]


def test_a_step_without_its_evaluation_is_left_out(summary, tmp_path):
    write_simple_trainer_run(tmp_path, [(1000, 10.0, 3.0, 20.0), (2000, 23.0, 4.0, 24.0)])
    (tmp_path / "stats" / "val_step0999.json").unlink()
    history = summary.simple_trainer_history(str(tmp_path))
    # step 1000's save and evaluation are unknown, so nothing is taken out of step 2000's clock
    assert [(p["step"], p["train_seconds"]) for p in history] == [(2000, pytest.approx(23.0))]


def test_time_to_a_level_is_the_first_evaluation_or_the_crossing_between_two(summary):
    curve = [{"step": 1000, "train_seconds": 10.0, "psnr": 20.0},
             {"step": 2000, "train_seconds": 20.0, "psnr": 24.0},
             {"step": 3000, "train_seconds": 30.0, "psnr": 23.0}]
    assert summary.seconds_by_interpolation(curve, 22.0) == pytest.approx(15.0)
    assert summary.seconds_by_interpolation(curve, 19.0) == pytest.approx(10.0)  # already at the first
    assert summary.seconds_by_interpolation(curve, 24.5) is None
    # the upper bound the bench uses agrees where a point reaches the level
    assert summary.seconds_to_reach(curve, 22.0) == 20.0
