"""eg-analyze on a tiny run: every command writes its figure and the numbers behind it."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest

from exploregs_plugin.analysis.branches import CURVES
from exploregs_plugin.analysis.probing import TrainSpec
from exploregs_plugin.analysis.sampling import evenly_spaced, probe_steps
from exploregs_plugin.scripts.analyze import Blending, GradBranches, main, parse

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _png(path: Path) -> None:
    assert path.read_bytes()[:8] == PNG_MAGIC and path.stat().st_size > 5000, path


def _csv(path: Path) -> list[dict[str, str]]:
    with open(path) as f:
        return list(csv.DictReader(f))


@pytest.fixture(scope="module")
def branches_run(tmp_path_factory, tiny_scene_dir):
    out = tmp_path_factory.mktemp("grad-branches")
    args = parse(["grad-branches", "--data", "builtin:tiny", "--max-steps", "20", "--every", "10",
                  "--views", "2", "--out", str(out)])  # fmt: skip
    assert isinstance(args, GradBranches) and args.train.max_steps == 20
    return out, main(args)


def test_grad_branches_trains_and_writes_curves(branches_run):
    out, result = branches_run
    _png(out / "grad_branches.png")
    rows = _csv(out / "grad_branches.csv")
    saved = json.loads((out / "grad_branches.json").read_text())
    assert [int(r["step"]) for r in rows] == [0, 10, 20] == [r["step"] for r in saved["rows"]]
    for row, kept in zip(rows, saved["rows"]):
        for name in CURVES:
            assert float(row[name]) == pytest.approx(kept[name])
        assert kept["mean2d"] > kept["cov"] > 0
        # the total is a vector sum: never larger than the sum of the branch norms
        assert kept["total"] <= kept["mean2d"] + kept["cov"] + kept["sh"] + 1e-12
    assert (out / "run" / "config.yml").is_file() and (out / "run" / "metrics.json").is_file()


def test_grad_branches_from_a_run_uses_its_checkpoints(branches_run, tmp_path):
    out, result = branches_run
    again = main(GradBranches(run=out / "run", views=2, out=tmp_path))
    _png(tmp_path / "grad_branches.png")
    assert [r["step"] for r in again["rows"]] == [20]
    # the final checkpoint reproduces the last probe of the training run exactly
    for name in CURVES:
        assert again["rows"][0][name] == pytest.approx(result["rows"][-1][name], rel=1e-6)


def test_grad_directions_writes_histograms(branches_run, tmp_path):
    out, _ = branches_run
    result = main(parse(["grad-directions", "--run", str(out / "run"), "--views", "3", "--bins", "10",
                         "--out", str(tmp_path)]))  # fmt: skip
    _png(tmp_path / "grad_directions.png")
    rows = _csv(tmp_path / "grad_directions.csv")
    assert len(rows) == len(CURVES) * 2 * 10
    summary = json.loads((tmp_path / "grad_directions.json").read_text())["summary"]
    assert summary["mean2d"]["ray"]["n"] > 0 and summary["mean2d"]["ray"]["max"] < 1e-4
    assert summary["cov"]["ray"]["median"] > 0.1
    for branch in ("mean2d", "cov"):
        fractions = [float(r["fraction"]) for r in rows if r["branch"] == branch and r["reference"] == "ray"]
        assert sum(fractions) == pytest.approx(1.0)
    assert result["step"] == 20


def test_blending_writes_pixel_and_rank_figures(branches_run, tmp_path):
    out, _ = branches_run
    result = main(parse(["blending", "--run", str(out / "run"), "--view", "1", "--out", str(tmp_path)]))
    for name in ("blending_pixel", "blending_ranks", "blending_visibility"):
        _png(tmp_path / f"{name}.png")
    pixel = json.loads((tmp_path / "blending_pixel.json").read_text())
    rows = pixel["rows"]
    assert list(result["xy"]) == pixel["pixel"] and len(result["pixel"]) == len(rows)
    assert len(rows) >= 2 and pixel["threshold_ndc"] == pytest.approx(0.0002)
    assert rows[0]["T_before"] == 1.0
    for a, b in zip(rows, rows[1:]):
        assert b["T_before"] == pytest.approx(a["T_before"] * (1 - a["alpha"]), rel=1e-5)
        assert b["depth"] >= a["depth"]
    ranks = _csv(tmp_path / "blending_ranks.csv")
    assert int(ranks[0]["rank"]) == 0 and float(ranks[0]["mean_T"]) == pytest.approx(1.0)
    assert [float(r["mean_T"]) for r in ranks] == sorted((float(r["mean_T"]) for r in ranks), reverse=True)
    # the chosen pixel is the busiest one: its Gaussian count is the deepest rank (capped at 40)
    assert len(ranks) == min(len(rows), 40)
    vis = _csv(tmp_path / "blending_visibility.csv")
    assert sum(int(r["gaussians"]) for r in vis) > 0 and float(vis[-1]["hi"]) == 1.0


def test_blending_rejects_bad_arguments(branches_run, tmp_path):
    out, _ = branches_run
    with pytest.raises(ValueError, match="needs a run"):
        main(Blending(out=tmp_path))
    with pytest.raises(ValueError, match="out of range"):
        main(Blending(run=out / "run", view=999, out=tmp_path))
    with pytest.raises(ValueError, match="outside"):
        main(Blending(run=out / "run", pixel=(1000, 0), out=tmp_path))
    # an explicit pixel traces exactly that pixel
    result = main(Blending(run=out / "run", view=0, pixel=(3, 4), max_rank=2, out=tmp_path / "explicit"))
    assert result["xy"] == (3, 4) and len(result["ranks"]) <= 2


def test_sampling_helpers():
    assert evenly_spaced(3, 10) == [0, 4, 9]
    assert evenly_spaced(5, 3) == [0, 1, 2]
    assert probe_steps(20, 8) == [0, 8, 16, 20]
    with pytest.raises(ValueError):
        probe_steps(20, 0)
    with pytest.raises(ValueError):
        evenly_spaced(2, 0)
    config = TrainSpec(data="builtin:tiny", max_steps=7).trainer_config(Path("/tmp/x"))
    assert config.max_steps == 7 and config.pipeline.datamanager.data == "builtin:tiny" and config.quiet
    assert config.data is None  # moved into the datamanager when the config was built
