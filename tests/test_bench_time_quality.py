"""The time-to-quality table (exploregs_plugin/bench/time_quality.py): seconds to each PSNR level,
ratios to the baseline, and the preset."""

from __future__ import annotations

from pathlib import Path

import pytest

from exploregs_plugin.bench.presets import time_to_quality as time_to_quality_preset
from exploregs_plugin.bench.runner import RunRecord
from exploregs_plugin.bench.spec import BenchEntry, BenchScene, BenchSpec
from exploregs_plugin.bench.time_quality import markdown_lines, seconds_to_reach, time_to_quality


def _history(points: list[tuple[int, float, float]]) -> list[dict]:
    return [{"step": step, "train_seconds": seconds, "psnr": psnr} for step, seconds, psnr in points]


def test_seconds_to_reach_is_the_first_evaluation_at_or_above_the_level():
    history = _history([(300, 30.0, 20.0), (100, 10.0, 18.0), (200, 20.0, 21.5), (400, 40.0, 21.0)])
    assert seconds_to_reach(history, 18.0) == 10.0  # reached exactly at the first evaluation
    assert seconds_to_reach(history, 21.0) == 20.0  # step order, not list order; a later dip is ignored
    assert seconds_to_reach(history, 21.6) is None
    assert seconds_to_reach([], 10.0) is None


def _record(scene: str, entry: str, psnr: float, history: list[dict], seed: int = 0, status: str = "done") -> RunRecord:
    metrics = {"psnr": psnr, "num_gaussians": 1000, "train_seconds": history[-1]["train_seconds"], "history": history}
    return RunRecord(scene, entry, seed, Path("/x"), status=status, metrics=metrics if status == "done" else None)


def _spec() -> BenchSpec:
    return BenchSpec(entries=(BenchEntry("default", "exploregs-default"), BenchEntry("fast", "exploregs-default")),
                     scenes=(BenchScene("s", "builtin:tiny"),))


def test_levels_follow_the_baseline_and_ratios_divide_by_its_seconds():
    base = _history([(100, 10.0, 19.0), (200, 20.0, 21.0), (300, 30.0, 21.6), (400, 40.0, 22.0)])
    fast = _history([(100, 4.0, 20.5), (200, 8.0, 21.8), (300, 12.0, 21.9), (400, 16.0, 21.95)])
    rows = time_to_quality(_spec(), [_record("s", "default", 22.0, base), _record("s", "fast", 21.95, fast)])
    default, quick = rows
    assert default["levels"] == pytest.approx([19.0, 20.0, 21.0, 21.5, 22.0])
    assert default["seconds"] == [10.0, 20.0, 20.0, 30.0, 40.0] and default["ratios"] == [1.0] * 5
    # "fast" reaches the first four levels sooner and never the baseline's final 22.0 dB
    assert quick["seconds"] == [4.0, 4.0, 8.0, 8.0, None]
    assert quick["ratios"][:4] == pytest.approx([0.4, 0.2, 0.4, 8.0 / 30.0]) and quick["ratios"][4] is None
    lines = markdown_lines(_spec(), rows)
    assert lines[0] == "`s`:"
    assert lines[2] == ("| method | s to 19.00 dB (-3) | s to 20.00 dB (-2) | s to 21.00 dB (-1) | s to 21.50 dB (-0.5) "
                        "| s to 22.00 dB (base) | final PSNR | Gaussians | train s |")
    assert lines[4] == "| default | 10.0 (1.00x) | 20.0 (1.00x) | 20.0 (1.00x) | 30.0 (1.00x) | 40.0 (1.00x) | 22.00 | 1000 | 40.0 (1.00x) |"
    assert lines[5] == "| fast | 4.0 (0.40x) | 4.0 (0.20x) | 8.0 (0.40x) | 8.0 (0.27x) | not reached | 21.95 | 1000 | 16.0 (0.40x) |"


def test_a_level_counts_as_reached_only_when_every_seed_reached_it():
    spec = BenchSpec(entries=(BenchEntry("default", "exploregs-default"),), scenes=(BenchScene("s", "builtin:tiny"),),
                     seeds=(0, 1))
    records = [_record("s", "default", 22.0, _history([(100, 10.0, 22.0)]), seed=0),
               _record("s", "default", 20.0, _history([(100, 14.0, 20.0)]), seed=1)]
    row, = time_to_quality(spec, records, below=(0.0, 2.0))
    assert row["levels"] == [21.0, 19.0]  # the mean final PSNR of the baseline's seeds
    assert row["seconds"] == [None, 12.0]


def test_a_scene_without_a_finished_baseline_says_so():
    rows = time_to_quality(_spec(), [_record("s", "default", 0.0, _history([(1, 1.0, 1.0)]), status="failed")])
    assert rows[0]["levels"] == []
    assert markdown_lines(_spec(), rows) == ["`s`: no finished `default` run, so no levels.", ""]


def test_the_preset_times_the_options_against_todays_default(tmp_path):
    for name in ("beer", "fox"):  # the captured scenes' folders, wherever ../shared/scenes is
        (tmp_path / name).mkdir()
    spec = time_to_quality_preset(tmp_path)
    assert [(s.name, s.options) for s in spec.scenes] == [("beer", ("--data-factor", "4")), (
        "fox", ("--data-factor", "4")), ("default", ("--max-steps", "1500"))]
    assert [e.name for e in spec.entries] == ["default", "c2f", "short", "c2f-short", "seedsplit", "seedsplit-c2f"]
    assert spec.baseline == "default" and spec.entry("default").overrides == ()
    assert spec.entry("c2f").overrides == ("--schedule.coarse-levels", "2")
    assert spec.eval_count >= 20
    assert spec.scenes[-1].data == "builtin:default"
