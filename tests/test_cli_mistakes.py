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
    from exploregs_plugin.engine.trainer import TrainerConfig

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
                                                                                          capsys,
                                                                                          sigint_as_in_a_terminal):
    import os
    import shlex
    import signal
    import time

    from exploregs_plugin.io.checkpoint import list_checkpoints
    from exploregs_plugin.engine.run_logger import RunLogger
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


def _mistakes(run: Path, ply: Path, dataset: Path, missing: Path) -> list[tuple[str, list[str], str]]:
    """(command, arguments, its one line): the sweep of issue 48 over every command."""
    R, P, D, M = str(run), str(ply), str(dataset), str(missing)
    is_run = f"{R}: an eg-train run, not a dataset: it trained on builtin:tiny (eg-train --resume {R} continues it)"
    is_dataset = (f"{D} is a dataset, not a run folder (it has no config.yml): eg-train METHOD --data {D} trains a run "
                  "on it")
    is_ply = f"{P} is a PLY of Gaussians, not a run folder or a checkpoint (.pt) of one"
    no_run = f"{M} is neither a run folder nor a checkpoint file"
    return [
        ("eg-train", ["exploregs-default", "--data", M], f"--data {M}: path does not exist (and is not builtin:NAME)"),
        ("eg-train", ["exploregs-default", "--data", R], is_run),
        ("eg-train", ["exploregs-default", "--data", P], f"{P}: a PLY of trained Gaussians, not a dataset"),
        ("eg-train", ["--resume", M], no_run),
        ("eg-train", ["--resume", D], is_dataset),
        ("eg-train", ["--resume", P], is_ply),
        ("eg-train", [D], f"{D} is a path, not a method: eg-train METHOD --data {D} trains on it (eg-train --help "
                          "lists the methods)"),
        ("eg-train", [R], f"{R} is an eg-train run, not a method: eg-train --resume {R} continues it"),
        ("eg-train", ["exploregs-default", "--data", D, "--cameras-from", R], "unrecognized option --cameras-from"),
        ("eg-train", ["exploregs-default", "--data", "builtin:tiny", "--run-dir", D],
         f"--run-dir {D} is a dataset; outputs never go into a dataset: pass a folder of its own as --run-dir"),
        ("eg-train", ["exploregs-default", "--data", "builtin:tiny", "--output-dir", f"{D}/images/runs"],
         f"--output-dir {D}/images/runs is inside the dataset {Path(D).resolve()}; outputs never go into a dataset: "
         "pass a folder of its own as --output-dir"),
        ("eg-eval", [], "missing PATH (eg-eval --help lists its options)"),
        ("eg-eval", [M], no_run),
        ("eg-eval", [D], is_dataset),
        ("eg-eval", [P], f"{P}: a PLY holds no cameras or images; pass --data DATASET to score it"),
        ("eg-eval", [P, "--data", R], is_run),
        ("eg-eval", [R, "--data", D], f"--data is for PLY input; {R} is a run, scored on the test views of its own "
                                      "dataset at the factor it trained at"),
        ("eg-eval", [R, "--max-steps", "3"], "unrecognized option --max-steps (eg-eval --help lists its options)"),
        ("eg-eval", [R, "--out", D], f"--out {D} is a dataset; outputs never go into a dataset: pass a folder of its "
                                     "own as --out"),
        ("eg-export", [M], no_run),
        ("eg-export", [D], is_dataset),
        ("eg-export", [P], is_ply),
        ("eg-export", [R, "--cameras-from", D],
         "unrecognized option --cameras-from (eg-export --help lists its options)"),
        ("eg-render", [M], no_run),
        ("eg-render", [D], is_dataset),
        ("eg-render", [P], f"{P}: a PLY holds no cameras; pass --cameras-from RUN_OR_DATASET (a run folder, a dataset "
                           "folder or builtin:NAME)"),
        ("eg-render", [P, "--cameras-from", P], f"{P}: a PLY of trained Gaussians, not a dataset"),
        ("eg-render", [R, "--cameras-from", D],
         f"--cameras-from is for PLY input; {R} is a run, which has its own cameras"),
        ("eg-render", [R, "--data", D], "unrecognized option --data (eg-render --help lists its options)"),
        ("eg-render", [R, "--out", f"{D}/images/frames"], f"--out {D}/images/frames is inside the dataset {D}; outputs "
                                                          "never go into a dataset: pass a folder of its own as --out"),
        ("eg-view", [M], f"{M}: no such run folder, checkpoint or PLY file"),
        ("eg-view", [D], is_dataset),
        ("eg-view", [R, "--data", D], "unrecognized option --data (eg-view --help lists its options)"),
        ("eg-view", [R, "--data-factor", "2"], f"--data-factor is for a PLY with --cameras-from; {R} is a run, shown "
                                               "at the factor it trained at"),
        ("eg-scenes", [], "missing a subcommand: one of make, list, stats (eg-scenes --help lists its options)"),
        ("eg-scenes", ["stats", M], f"{M}: no such folder"),
        ("eg-scenes", ["stats", R], f"{R}: not a scene written by eg-scenes make (it has no scene.json)"),
        ("eg-scenes", ["list", "--data", D], "unrecognized option --data (eg-scenes --help lists its options)"),
        ("eg-analyze", ["blending", "--run", M], no_run),
        ("eg-analyze", ["blending", "--run", D], is_dataset),
        ("eg-analyze", ["blending", "--run", P], is_ply),
        ("eg-analyze", ["blending", "--run", R, "--data", D],
         "unrecognized option --data (eg-analyze --help lists its options)"),
        ("eg-analyze", ["grad-branches", "--data", R, "--out", f"{M}-out"], is_run),
        ("eg-analyze", [R], f"unrecognized argument {R} (a subcommand comes first: grad-branches, grad-directions, "
                            "blending, nearside) (eg-analyze --help lists its options)"),
        ("eg-bench", ["--out", f"{M}-bench", "--spec", P], f"spec file {P}: not a YAML or JSON text file"),
        ("eg-bench", ["--out", f"{M}-bench", "--scenes", M, "--methods", "default", "--dry-run"],
         f"scene {M}: path does not exist (and is not builtin:NAME)"),
        ("eg-bench", ["--out", f"{M}-bench", "--scenes", R, "--methods", "default"], f"scene {is_run}"),
        ("eg-bench", ["--out", f"{M}-bench", "--data", D],
         "unrecognized option --data (eg-bench --help lists its options)"),
    ]


ENTRYPOINTS = {"eg-train": "train", "eg-eval": "eval", "eg-export": "export", "eg-render": "render", "eg-view": "view",
               "eg-scenes": "scenes", "eg-analyze": "analyze", "eg-bench": "bench"}


def test_every_commands_mistakes_give_one_true_line_and_exit_code_2(run, ply, tiny_scene_dir, tmp_path, monkeypatch,
                                                                     capsys):
    import importlib
    import signal

    import torch

    from exploregs_plugin.runtime import threads

    sigterm = signal.getsignal(signal.SIGTERM)  # eg-train and eg-view set their own
    # every command measures the idle CPUs for 0.2 s before it reads its arguments: 42 commands here
    # would wait 8 s for a thread count that no mistake depends on
    monkeypatch.setattr(threads, "default_threads", lambda measure_seconds=0.2: torch.get_num_threads())
    wrong = []
    cases = _mistakes(run, ply, tiny_scene_dir, tmp_path / "missing")
    assert {command for command, _, _ in cases} == set(ENTRYPOINTS)  # every command
    try:
        for command, argv, line in cases:
            module = importlib.import_module(f"exploregs_plugin.scripts.{ENTRYPOINTS[command]}")
            monkeypatch.setattr(sys, "argv", [command, *argv])
            capsys.readouterr()
            with pytest.raises(SystemExit) as exit_:
                module.entrypoint()
            out, err = capsys.readouterr()
            got = [ln for ln in (out + err).splitlines() if ln.strip()]
            if exit_.value.code != 2 or got != [f"{command}: error: {line}"]:
                wrong.append((command, argv, exit_.value.code, got))
    finally:
        signal.signal(signal.SIGTERM, sigterm)
    assert wrong == []
    assert not (tmp_path / "missing-out").exists() and not (tmp_path / "missing-bench").exists()


def test_a_warning_is_one_line_naming_the_command_and_python_form_comes_back(monkeypatch):
    """A dataset's note (3 of 59 photos not in the model, ...) reaches the user as one line, not as
    Python's file:line: UserWarning plus the source line of the code that warned."""
    import warnings

    monkeypatch.delenv("EXPLOREGS_DEBUG", raising=False)
    before = warnings.formatwarning
    text = run_cli("eg-train", lambda _: warnings.formatwarning(
        UserWarning("/data/images: 3 of 59 images are not in the COLMAP model"), UserWarning, "colmap.py", 253,
        "warnings.warn(...)"), [])
    assert text == "eg-train: warning: /data/images: 3 of 59 images are not in the COLMAP model\n"
    assert warnings.formatwarning is before
    monkeypatch.setenv("EXPLOREGS_DEBUG", "1")  # the developer's form: where it came from
    text = run_cli("eg-train", lambda _: warnings.formatwarning(UserWarning("x"), UserWarning, "colmap.py", 253), [])
    assert "colmap.py:253: UserWarning: x" in text
