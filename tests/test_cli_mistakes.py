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
    assert err.strip().splitlines() == [
        f"eg-train: error: --data {missing}: path does not exist (and is not builtin:NAME)"]
    export.main(export.ExportArgs(run, out=tmp_path / "s.ply"))  # renders nothing: no renderer line
    assert [ln.split(" ")[0] for ln in capsys.readouterr().out.splitlines()] == ["wrote"]
    eval_script.main(eval_script.EvalArgs(run, out=tmp_path / "eval", save_images=False))  # renders
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 2 and lines[0].startswith("renderer: ") and lines[1].startswith("PSNR ")


TINY_RUN = ["exploregs-default", "--data", "builtin:tiny", "--no-tensorboard", "--quiet", "--eval-count", "1",
            "--no-save-eval-images"]


def test_ctrl_c_before_the_first_checkpoint_says_nothing_was_saved_and_how_to_start_again(tmp_path, monkeypatch,
                                                                                          capsys):
    import os
    import shlex
    import signal
    import time

    from exploregs_plugin.io.checkpoint import list_checkpoints
    from exploregs_plugin.run_logger import RunLogger
    from exploregs_plugin.scripts import train

    run_dir = tmp_path / "run"
    argv = [*TINY_RUN, "--max-steps", "3", "--run-dir", str(run_dir)]
    real_enter = RunLogger.__enter__

    def ctrl_c(self):  # a real Ctrl-C after the run folder is made, before the loop takes over the signal
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(5)
        return real_enter(self)

    monkeypatch.setattr(RunLogger, "__enter__", ctrl_c)
    with pytest.raises(SystemExit) as exit_:
        run_cli("eg-train", train.main, argv)
    assert exit_.value.code == 130
    assert (run_dir / "config.yml").is_file() and list_checkpoints(run_dir) == []
    assert capsys.readouterr().err.strip().splitlines()[-1] == (
        "eg-train: error: interrupted; no checkpoint was saved, so there is nothing to resume; start again with: "
        f"eg-train {shlex.join(argv)}")
    monkeypatch.setattr(RunLogger, "__enter__", real_enter)
    assert run_cli("eg-train", train.main, shlex.split(shlex.join(argv)))["steps"] == 3  # the command it names runs


def test_a_stop_names_the_last_finished_step_and_the_checkpoint_that_holds_it(tmp_path, ctrl_c_after_step, capsys):
    from exploregs_plugin.io.checkpoint import latest_checkpoint, load_checkpoint
    from exploregs_plugin.scripts import train

    run_dir = tmp_path / "run"
    ctrl_c_after_step.arm(3)  # Ctrl-C during the 4th step: it finishes, then the run stops
    with pytest.raises(SystemExit) as exit_:
        run_cli("eg-train", train.main, [*TINY_RUN, "--max-steps", "50", "--run-dir", str(run_dir)])
    ctrl_c_after_step.disarm()
    assert exit_.value.code == 130
    checkpoint = latest_checkpoint(run_dir)
    assert checkpoint.name == "step-0000004.pt" and load_checkpoint(checkpoint)["step"] == 4
    assert capsys.readouterr().err.strip().splitlines()[-1] == (
        f"eg-train: error: stopped by SIGINT after step 4, saved in {checkpoint}; "
        f"resume with: eg-train --resume {run_dir}")
