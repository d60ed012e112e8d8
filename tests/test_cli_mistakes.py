"""What a new user gets wrong with the commands, and the one true line each gives (exit code 2):
missing or wrong paths, a run folder where a dataset is expected and the reverse, a PLY where a run
is expected, flags from another command. Also which commands print the renderer line, and when."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from exploregs_plugin.scripts import run_cli


@pytest.fixture(scope="module")
def run(tmp_path_factory, exploregs_cache) -> Path:
    from exploregs_plugin.trainer import TrainerConfig

    run_dir = tmp_path_factory.mktemp("mistakes") / "run"
    TrainerConfig(data="builtin:tiny", max_steps=2, run_dir=run_dir, quiet=True, tensorboard=False, eval_count=1,
                  save_eval_images=False).setup().train()
    return run_dir


@pytest.fixture(scope="module")
def ply(run) -> Path:
    from exploregs_plugin.scripts import export

    return export.main(export.ExportArgs(run, out=run.parent / "scene.ply")).path


def test_the_renderer_line_comes_from_commands_that_render_after_the_data_are_read(run, tmp_path, capsys):
    from exploregs_plugin.scripts import eval as eval_script
    from exploregs_plugin.scripts import export, train

    capsys.readouterr()
    missing = tmp_path / "missing"
    with pytest.raises(SystemExit) as exit_:
        run_cli("eg-train", train.main, ["exploregs-default", "--data", str(missing)])
    out, err = capsys.readouterr()
    assert exit_.value.code == 2 and out == ""  # the data error is the first and only line
    assert err.strip().splitlines() == [f"eg-train: error: --data {missing}: path does not exist (and is not builtin:NAME)"]
    export.main(export.ExportArgs(run, out=tmp_path / "s.ply"))  # renders nothing: no renderer line
    assert [ln.split(" ")[0] for ln in capsys.readouterr().out.splitlines()] == ["wrote"]
    eval_script.main(eval_script.EvalArgs(run, out=tmp_path / "eval", save_images=False))  # renders
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 2 and lines[0].startswith("renderer: ") and lines[1].startswith("PSNR ")
