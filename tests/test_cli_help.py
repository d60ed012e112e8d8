"""--help text: one flag per setting, sentences not broken where the source wraps, no "(default: None)"
where unset has a meaning to say."""

from __future__ import annotations

import functools
import re

import pytest

from exploregs_plugin.io.config_files import join_help_lines


def _help(capsys, monkeypatch, run, width: int = 120) -> str:
    monkeypatch.setenv("COLUMNS", str(width))
    with pytest.raises(SystemExit) as exit_:
        run()
    assert exit_.value.code in (0, None)
    captured = capsys.readouterr()
    return captured.out + captured.err


def test_join_help_lines_keeps_paragraphs_lists_and_examples():
    text = "First line, and\n    continues (here)\n    and 3 ends.\n\n    Next:\n    - one\n    - two\n        example"
    assert join_help_lines(text) == "First line, and continues (here) and 3 ends.\n\nNext:\n- one\n- two\n    example"


def test_eg_train_help_one_flag_per_setting_and_whole_sentences(capsys, monkeypatch):
    import exploregs_plugin.scripts  # noqa: F401  (the commands' help settings)
    from exploregs_plugin.scripts.train import parse_config

    text = _help(capsys, monkeypatch, lambda: parse_config(["exploregs-seedsplit", "--help-full"]))
    # --data and --datamanager.data are one setting: one entry names both flags
    assert text.count("--data STR, --datamanager.data STR") == 1 and text.count("--data ") == 1
    assert text.count("--data-factor INT, --datamanager.data-factor INT") == 1
    # a docstring's lines are joined: the source breaks after "(0 = off),", the help does not
    assert any("since the last (0 = off), so a kill -9" in line for line in text.splitlines())
    assert "(default: )" not in text
    # both flags still set the same field, the later one winning
    config = parse_config(["exploregs-default", "--data", "builtin:tiny", "--data-factor", "2"])
    assert (config.pipeline.datamanager.data, config.pipeline.datamanager.data_factor) == ("builtin:tiny", 2)
    config = parse_config(["exploregs-default", "--datamanager.data", "builtin:farside", "--datamanager.data-factor", "3"])
    assert (config.pipeline.datamanager.data, config.pipeline.datamanager.data_factor) == ("builtin:farside", 3)


def _flags(text: str) -> set[str]:
    return set(re.findall(r"(?<![\w-])(--[a-z][\w.-]*[\w])", text))


def test_eg_train_method_help_is_one_line_per_flag_and_keeps_every_flag(capsys, monkeypatch):
    from exploregs_plugin.scripts.train import parse_config

    full = _help(capsys, monkeypatch, lambda: parse_config(["exploregs-seedsplit", "--help-full"]), width=80)
    short = _help(capsys, monkeypatch, lambda: parse_config(["exploregs-seedsplit", "--help"]), width=80)
    flag_lines = [line for line in full.splitlines() if line.startswith("│ -")]
    assert len(short.splitlines()) <= len(full.splitlines()) / 3
    assert _flags("\n".join(flag_lines)) <= _flags(short)  # every flag is still there, once
    assert short.count("\n  --max-steps INT ") == 1 and "[1500]" in short.split("--max-steps INT", 1)[1].split("\n")[0]
    assert all(len(line) <= 100 for line in short.splitlines() if line.startswith("  -"))
    assert "strategy options: Densification / exploration strategy" in short
    assert short.rstrip().endswith("eg-train METHOD --help-full")
    # another strategy's flags show with --strategy NAME
    swapped = _help(capsys, monkeypatch, lambda: parse_config(["exploregs-default", "--strategy", "mcmc", "--help"]))
    assert "--strategy.noise.lr" in swapped and "--strategy.seeding.n-seed" not in swapped


def test_a_methods_help_names_the_strategy_selector(capsys, monkeypatch):
    from exploregs_plugin.scripts.train import parse_config
    from exploregs_plugin.strategies.registry import builtin_strategies

    short = _help(capsys, monkeypatch, lambda: parse_config(["exploregs-seedsplit", "--help"]))
    lines = short.splitlines()
    # first in the strategy's group, with the method's own strategy as its default
    at = next(i for i, line in enumerate(lines) if line.startswith("strategy options:")) + 1
    assert re.fullmatch(r"  --strategy NAME +Use another registered strategy, with its own flags \[seedsplit\]",
                        lines[at])
    # then every registered strategy, on lines indented to the descriptions' column
    below = [line for line in lines[at + 1:at + 6] if line.startswith(" " * 33)]
    listed = " ".join(line.strip() for line in below)
    assert listed.startswith("one of: ") and set(builtin_strategies()) <= {n.strip(",") for n in listed.split()[2:]}
    assert all(len(line) <= 100 for line in [lines[at], *below])
    # the whole help names it too, after tyro's boxes
    full = _help(capsys, monkeypatch, lambda: parse_config(["exploregs-mcmc", "--help-full"]))
    assert "\nstrategy selector:\n  --strategy NAME" in full and "own flags [mcmc]" in full


def test_eg_bench_help_says_what_unset_means(capsys, monkeypatch):
    from exploregs_plugin.scripts.bench import main

    text = _help(capsys, monkeypatch, lambda: main(["--help"]))
    assert "(default: None)" not in text and "(repeatable). (repeatable)" not in text
    assert "(default: the preset's or spec file's, else 1000)" in text


def test_eg_process_help_says_its_input_is_required(capsys, monkeypatch):
    from exploregs_plugin.scripts.process import parse_args

    text = _help(capsys, monkeypatch, lambda: parse_args(["--help"]))
    assert "(default: )" not in text
    assert "Never written to. (required)" in " ".join(text.replace("│", " ").split())


@functools.lru_cache(maxsize=None)
def _documented(cls: type) -> frozenset[str]:
    """The fields of ``cls`` that a class of its MRO documents with a docstring (docstring_parser's
    attribute docstrings, the reader tyro asks first; it parses the class's source)."""
    import docstring_parser

    return frozenset(param.arg_name for klass in cls.__mro__ if klass.__module__ != "builtins"
                     for param in docstring_parser.parse_from_object(klass).params if param.description)


def _undocumented_fields(config, seen: set[int]) -> list[str]:
    """``Class.field`` for every field of ``config`` and of the dataclasses it holds that has no
    docstring."""
    import dataclasses

    if id(config) in seen:
        return []
    seen.add(id(config))
    missing = []
    for field in dataclasses.fields(config):
        if field.name not in _documented(type(config)):
            missing.append(f"{type(config).__qualname__}.{field.name}")
        value = getattr(config, field.name)
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            missing += _undocumented_fields(value, seen)
    return missing


def test_every_setting_of_every_method_and_strategy_has_a_docstring():
    """A setting without a docstring has no help line, and tyro then looks for a comment by
    tokenizing the source of its whole class, on every parse (it clears its caches after each):
    four nested configs without one (the schedule, the datamanager, the model, the optimizer)
    made every eg-train parse read and tokenize the trainer's and the pipeline's modules, about
    half of a parse's time (docs/training.md, "Startup")."""
    from dataclasses import replace

    from exploregs_plugin.method_configs import all_methods
    from exploregs_plugin.strategies.registry import available_strategies

    def ours(kind: type) -> bool:  # not a plug-in's
        return kind.__module__.startswith("exploregs_plugin.")

    configs = [method.config for method in all_methods().values() if ours(type(method.config.pipeline.strategy))]
    base = configs[0]
    configs += [replace(base, pipeline=replace(base.pipeline, strategy=strategy()))
                for strategy in available_strategies().values() if ours(strategy)]
    seen: set[int] = set()
    missing = sorted({name for config in configs for name in _undocumented_fields(config, seen)})
    assert missing == []
