"""eg-scenes: `make` writes a loadable scene with the requested settings; `list` shows presets."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from exploregs_plugin.data import ParseOptions, read_colmap
from exploregs_plugin.data.builtin import PRESETS
from exploregs_plugin.scripts.scenes import main


def test_make_writes_a_loadable_scene(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    out = tmp_path / "fs"
    argv = ["make", "farside", "--out", str(out), "--width", "24", "--height", "16",
            "--views", "3", "--seed", "2", "--points", "50"]
    assert main(argv) == 0
    assert "wrote farside (24x16, 3 views, seed 2)" in capsys.readouterr().out
    scene = read_colmap(out, ParseOptions())
    assert [im.name for im in scene.images] == ["0000.png", "0001.png", "0002.png"]
    assert all((im.width, im.height) == (24, 16) for im in scene.images)
    assert scene.points.shape == (50, 3)
    meta = json.loads((out / "scene.json").read_text())
    assert meta["preset"]["layout"] == "farside" and meta["preset"]["seed"] == 2 and meta["seconds"] > 0
    # refuses to overwrite unless asked
    assert main(argv) == 2
    assert "not empty" in capsys.readouterr().err
    assert main(argv + ["--overwrite"]) == 0


def test_make_unknown_preset(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    assert main(["make", "nowhere", "--out", str(tmp_path / "x")]) == 2
    assert "unknown built-in scene" in capsys.readouterr().err


def test_list_prints_every_preset(capsys: pytest.CaptureFixture) -> None:
    assert main(["list"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    header = lines[0].split()
    assert header[:4] == ["name", "layout", "width", "height"] and len(lines) == len(PRESETS) + 1
    rows = {line.split()[0]: dict(zip(header, line.split())) for line in lines[1:]}
    for name, preset in PRESETS.items():
        assert rows[name]["width"] == str(preset.width) and rows[name]["layout"] == preset.layout
    assert main(["list", "--json"]) == 0
    settings = json.loads(capsys.readouterr().out)
    assert settings["default"]["n_views"] == PRESETS["default"].n_views and set(settings) == set(PRESETS)


def test_stats_describes_a_generated_scene(tiny_scene_dir: Path, tmp_path: Path,
                                           capsys: pytest.CaptureFixture) -> None:
    assert main(["stats", str(tiny_scene_dir)]) == 0
    stats = json.loads(capsys.readouterr().out)
    assert (stats["train_views"], stats["test_views"], stats["points"]) == (8, 2, 400)
    shares = stats["test_other_share"] + stats["test_far_share"] + stats["test_occluded_share"]
    assert shares == pytest.approx(1.0)
    assert 0 < stats["far_points_share"] < stats["test_far_share"]
    assert main(["stats", str(tmp_path)]) == 2
    assert "not a generated scene" in capsys.readouterr().err
