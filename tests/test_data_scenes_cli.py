"""eg-scenes: `make` writes a loadable scene with the requested settings; `list` shows presets."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from exploregs_plugin.data import ParseOptions, read_colmap
from exploregs_plugin.data.builtin.presets import PRESETS
from exploregs_plugin.data.builtin.dynamic import DYNAMIC_PRESETS
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
    static, dynamic = capsys.readouterr().out.strip().split("\n\ndynamic scenes:\n")
    lines = static.splitlines()
    header = lines[0].split()
    assert header[:4] == ["name", "layout", "width", "height"] and len(lines) == len(PRESETS) + 1
    rows = {line.split()[0]: dict(zip(header, line.split())) for line in lines[1:]}
    for name, preset in PRESETS.items():
        assert rows[name]["width"] == str(preset.width) and rows[name]["layout"] == preset.layout
    lines = dynamic.splitlines()
    header = lines[0].split()
    assert header[:5] == ["name", "width", "height", "n_cameras", "n_frames"]
    rows = {line.split()[0]: dict(zip(header, line.split())) for line in lines[1:]}
    assert set(rows) == set(DYNAMIC_PRESETS)
    assert rows["dynamic"]["n_frames"] == str(DYNAMIC_PRESETS["dynamic"].n_frames)
    assert main(["list", "--json"]) == 0
    settings = json.loads(capsys.readouterr().out)
    assert settings["default"]["n_views"] == PRESETS["default"].n_views
    assert set(settings) == set(PRESETS) | set(DYNAMIC_PRESETS)


def test_stats_describes_a_generated_scene(tiny_scene_dir: Path, tmp_path: Path,
                                           capsys: pytest.CaptureFixture) -> None:
    assert main(["stats", str(tiny_scene_dir)]) == 0
    stats = json.loads(capsys.readouterr().out)
    assert (stats["train_views"], stats["test_views"], stats["points"]) == (8, 2, 400)
    shares = stats["test_other_share"] + stats["test_far_share"] + stats["test_occluded_share"]
    assert shares == pytest.approx(1.0)
    assert 0 < stats["far_points_share"] < stats["test_far_share"]
    assert main(["stats", str(tmp_path)]) == 2
    assert "not a scene written by eg-scenes make (it has no scene.json)" in capsys.readouterr().err


def test_make_and_describe_a_dynamic_scene(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    out = tmp_path / "dyn"
    assert main(["make", "dynamic-tiny", "--out", str(out), "--cameras", "3", "--frames", "4"]) == 0
    assert "3 cameras x 4 frames" in capsys.readouterr().out
    assert sorted(p.name for p in out.glob("cam*")) == ["cam00", "cam01", "cam02"]
    assert len(list((out / "cam01" / "images").glob("*.png"))) == 4
    assert main(["stats", str(out)]) == 0
    stats = json.loads(capsys.readouterr().out)
    assert stats["train_views"] == 8 and stats["test_views"] == 4 and stats["test_moving_share"] > 0
    assert main(["make", "dynamic-tiny", "--out", str(tmp_path / "x"), "--views", "3"]) == 2
    assert "set --cameras and --frames" in capsys.readouterr().err
    assert main(["make", "tiny", "--out", str(tmp_path / "y"), "--frames", "3"]) == 2
    assert "static scene: set --views" in capsys.readouterr().err
