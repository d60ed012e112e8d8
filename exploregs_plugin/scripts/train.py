"""eg-train: train a method on a dataset.

    eg-train exploregs-seedsplit --data PATH        # train
    eg-train --resume RUN_DIR [--device DEVICE] [--machine.num-devices N]   # continue a run
    eg-train exploregs-seedsplit --data PATH --machine.num-devices 2   # 2 data-parallel ranks
    torchrun --nproc-per-node 2 -m exploregs_plugin.scripts.train exploregs-seedsplit --data PATH
"""

from __future__ import annotations

import contextlib
import io
import shlex
import signal
import sys
import textwrap
from dataclasses import replace
from pathlib import Path

import tyro

from exploregs_plugin.engine.collapse import CollapseError
from exploregs_plugin.io.config_files import compact_help, load_config, tyro_error_text
from exploregs_plugin.runtime.distributed import (LAUNCHER_GONE, DistributedError, MachineConfig, PeerLostError,
                                          launched_by_eg_train, launched_by_torchrun, leave_world)
from exploregs_plugin.io.checkpoint import check_output_folder, resolve_run
from exploregs_plugin.scripts import run_cli
from exploregs_plugin.method_configs import MethodRegistryError, all_methods, strategy_choice, with_strategy
from exploregs_plugin.engine.pipeline import NonFiniteError, resolve_batch_size
from exploregs_plugin.scripts.launch import LaunchError, LaunchStopped, launch, note_run_dir
from exploregs_plugin.engine.trainer import CONFIG_NAME, Stopped, Trainer, TrainerConfig


DESCRIPTION = ("Train a 3D Gaussian Splatting scene with ExploreGS. Any method can take any registered "
               "strategy (built-in or from a plugin) with: eg-train METHOD --strategy NAME. Continue an "
               "interrupted run with: eg-train --resume RUN_DIR [--device DEVICE] [--machine.num-devices N].")
RESUME_USAGE = "usage: eg-train --resume RUN_DIR [--device auto|cpu|cuda|cuda:N] [--machine.num-devices N]"


def _fail(message: str, code: int) -> "SystemExit":
    print(f"eg-train: error: {message}", file=sys.stderr)
    return SystemExit(code)


def parse_config(argv: list[str]) -> TrainerConfig:
    """Turn the command line into a TrainerConfig (one tyro subcommand per method; ``--strategy
    NAME`` swaps the method's strategy for a registered one before the rest is parsed)."""
    try:
        methods = all_methods()
    except MethodRegistryError as err:
        raise _fail(str(err), 2) from err
    if argv and not argv[0].startswith("-") and argv[0] not in methods and Path(argv[0]).expanduser().exists():
        if (Path(argv[0]).expanduser() / CONFIG_NAME).is_file():
            raise _fail(f"{argv[0]} is an eg-train run, not a method: eg-train --resume {shlex.quote(argv[0])} "
                        "continues it", 2)
        raise _fail(f"{argv[0]} is a path, not a method: eg-train METHOD --data {shlex.quote(argv[0])} "
                    "trains on it (eg-train --help lists the methods)", 2)
    if argv and not argv[0].startswith("-") and argv[0] not in methods:
        raise _fail(f"unknown method {argv[0]!r}; known methods: {', '.join(sorted(methods))}", 2)
    try:
        argv, strategy_name = strategy_choice(argv)
    except MethodRegistryError as err:
        raise _fail(str(err), 2) from err
    full_help = "--help-full" in argv  # tyro's whole help; --help shows one line per flag
    argv = ["--help" if arg == "--help-full" else arg for arg in argv]
    defaults = {name: spec.config for name, spec in methods.items()}
    if strategy_name is not None:
        if not argv or argv[0].startswith("-"):
            raise _fail("--strategy NAME needs a method first: eg-train METHOD --strategy NAME", 2)
        try:
            defaults[argv[0]] = with_strategy(defaults[argv[0]], strategy_name, methods)
        except MethodRegistryError as err:
            raise _fail(str(err), 2) from err
    subcommands = tyro.extras.subcommand_type_from_defaults(
        defaults, {name: spec.description for name, spec in methods.items()})
    captured, shown = io.StringIO(), _Utf8Text()
    try:
        with contextlib.redirect_stderr(captured), contextlib.redirect_stdout(shown):
            return tyro.cli(subcommands, args=argv, description=DESCRIPTION)
    except SystemExit as exit_:
        if exit_.code in (0, None):  # --help (tyro writes it to stdout)
            text = shown.getvalue()
            if argv and not argv[0].startswith("-"):  # a method's flags
                text = _method_help(text, defaults[argv[0]].pipeline.strategy, full_help)
            sys.stdout.write(text)
            sys.stderr.write(captured.getvalue())
            raise
        raise _fail(tyro_error_text(captured.getvalue()) or f"invalid arguments {argv}", 2) from None


def _strategy_selector_lines(strategy: object, width: int = 100) -> list[str]:
    """The help lines of ``--strategy NAME``, which tyro does not list (eg-train takes it out of
    the command line before tyro parses it): the method's strategy and every registered one, in
    the columns of ``compact_help``'s flag lines."""
    from exploregs_plugin.strategies.registry import StrategyPluginError, available_strategies, builtin_strategies

    broken = ""
    try:
        registered = available_strategies()
    except StrategyPluginError as err:  # a broken plugin must not hide the method's help: it is named
        registered, broken = builtin_strategies(), f" (plugins not listed: {err})"
    current = next((name for name, cls in registered.items() if type(strategy) is cls), type(strategy).__name__)
    indent = " " * 33  # where compact_help's flag descriptions start
    head = f"  {'--strategy NAME':<30} Use another registered strategy, with its own flags [{current}]"
    names = textwrap.wrap("one of: " + ", ".join(sorted(registered)) + broken, width, initial_indent=indent,
                          subsequent_indent=indent, break_on_hyphens=False)
    return [head, *names]


def _method_help(text: str, strategy: object, full_help: bool) -> str:
    """A method's help from tyro's, naming ``--strategy NAME``: compact (one line per flag) with
    the selector first in the strategy's group, or whole (``--help-full``) with it after the boxes."""
    lines = _strategy_selector_lines(strategy)
    if full_help:
        return text.rstrip("\n") + "\nstrategy selector:\n" + "\n".join(lines) + "\n"
    out = compact_help(text).splitlines()
    at = next((i + 1 for i, line in enumerate(out) if line.startswith("strategy options:")), len(out))
    return "\n".join(out[:at] + lines + out[at:]) + "\nEvery flag's whole description: eg-train METHOD --help-full\n"


class _Utf8Text(io.StringIO):
    """A text buffer that says it takes UTF-8, so tyro draws its help boxes as on a terminal
    (``compact_help`` reads those)."""

    @property
    def encoding(self) -> str:  # type: ignore[override]
        return "utf-8"


def _stop_before_training(signum: int, frame: object) -> None:
    signal.signal(signum, signal.SIG_IGN)  # a repeat (the launcher's SIGHUP comes once per thread) adds nothing
    raise Stopped(signum)


def _how_to_go_on(trainer: Trainer | None, argv: list[str]) -> str:
    """The end of a stop line, true to what is on disk: resume when the run has a checkpoint (one
    written now, one resumed from), else that nothing was saved and the command that starts it again."""
    if trainer is not None and trainer.last_checkpoint is not None:
        return f"resume with: eg-train --resume {shlex.quote(str(trainer.run_dir))}"
    if argv[:1] == ["--resume"]:  # stopped while loading the run: its checkpoints are as they were
        return f"resume with: eg-train {shlex.join(argv)}"
    return f"no checkpoint was saved, so there is nothing to resume; start again with: eg-train {shlex.join(argv)}"


def resume_options(argv: list[str]) -> tuple[Path, str | None, int | None]:
    """``--resume RUN_DIR [--device D] [--machine.num-devices N]`` -> (run, device, num_devices)."""
    if len(argv) < 2 or len(argv) % 2:
        raise _fail(RESUME_USAGE, 2)
    options = dict(zip(argv[2::2], argv[3::2]))
    if set(options) - {"--device", "--machine.num-devices"} or len(options) != (len(argv) - 2) // 2:
        raise _fail(RESUME_USAGE, 2)
    devices = options.get("--machine.num-devices")
    if devices is not None and not (devices.isdigit() and int(devices) >= 1):
        raise _fail(f"--machine.num-devices must be a positive integer, got {devices!r}", 2)
    return Path(argv[1]), options.get("--device"), None if devices is None else int(devices)


def _machine(argv: list[str], resume: tuple[Path, str | None, int | None] | None
             ) -> tuple[MachineConfig, TrainerConfig | None]:
    """The run's machine settings (from the command line, or the resumed run's config.yml),
    checked against its batch before any rank starts."""
    if resume is not None:
        run, _, devices = resume
        saved = load_config(resolve_run(run)[0] / CONFIG_NAME)
        machine = saved.machine if devices is None else replace(saved.machine, num_devices=devices)
        resolve_batch_size(saved.pipeline.batch_size, machine.world_size)
        return machine, None
    config = parse_config(argv)
    resolve_batch_size(config.pipeline.batch_size, config.machine.world_size)
    for flag, folder in (("--run-dir", config.run_dir), ("--output-dir", config.output_dir)):
        if folder is not None:  # the run would be written into it
            check_output_folder(flag, Path(folder))
    return config.machine, config


def main(argv: list[str]) -> dict:
    # Before the loop installs its own handler, SIGTERM ends the command with one line (pycolmap's
    # failure handler would otherwise print a crash dump); during training it checkpoints first.
    for signum in (signal.SIGTERM, LAUNCHER_GONE) if launched_by_eg_train() else (signal.SIGTERM,):
        signal.signal(signum, _stop_before_training)
    trainer = None
    try:
        resume = resume_options(argv) if argv[:1] == ["--resume"] else None
        machine, config = _machine(argv, resume)
        if machine.world_size > 1 and not launched_by_torchrun():
            launch(machine, argv)  # the ranks run this same command under torch's launcher
            return {}
        if resume is not None:
            run, device, devices = resume
            trainer = Trainer.from_run(run, device=device, num_devices=devices)
            if trainer.world.is_main:
                print(f"resuming {trainer.run_dir} from step {trainer.start_step} ({trainer.last_checkpoint})",
                      file=sys.stderr)
        else:
            trainer = config.setup()
        if trainer.world.is_main:
            print(f"run folder: {trainer.run_dir}", file=sys.stderr)
            note_run_dir(trainer.run_dir)
        metrics = trainer.train()
    except LaunchStopped as err:  # rank 0 printed where it stopped
        raise SystemExit(err.exit_code) from None
    except Stopped as err:
        if trainer is not None and not trainer.world.is_main:  # rank 0 speaks for the run
            raise SystemExit(err.exit_code) from None
        raise _fail(f"{err}; {_how_to_go_on(trainer, argv)}", err.exit_code) from None
    except KeyboardInterrupt:
        raise _fail(f"interrupted; {_how_to_go_on(trainer, argv)}", 130) from None
    except PeerLostError as err:
        if launched_by_eg_train():  # the launcher names the rank that was lost
            raise SystemExit(1) from None
        raise _fail(str(err), 1) from err
    except (NonFiniteError, CollapseError, DistributedError, LaunchError) as err:
        raise _fail(str(err), 1) from err
    finally:
        if trainer is not None and trainer.world.is_distributed:
            # the launcher stops the other ranks with SIGTERM when one fails: the run is over, so
            # leaving the group must not turn that signal into a second error
            signal.signal(signal.SIGTERM, signal.SIG_DFL)
            leave_world(trainer.world)
    if trainer.world.is_main:
        print(f"done: test PSNR {metrics['psnr']:.2f} dB, SSIM {metrics['ssim']:.4f}, "
              f"{metrics['num_gaussians']} Gaussians, {metrics['train_seconds']:.1f} s training, "
              f"{metrics['wall_seconds']:.1f} s in all (evaluation and checkpoints included); "
              f"metrics in {trainer.run_dir / 'metrics.json'}", file=sys.stderr)
    return metrics


def entrypoint() -> None:
    run_cli("eg-train", main, sys.argv[1:])


if __name__ == "__main__":
    entrypoint()
