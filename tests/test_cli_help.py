"""--help text: one flag per setting, sentences not broken where the source wraps, no "(default: None)"
where unset has a meaning to say."""

from __future__ import annotations

import pytest

from exploregs_plugin.configs import join_help_lines


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

    text = _help(capsys, monkeypatch, lambda: parse_config(["exploregs-seedsplit", "--help"]))
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


def test_eg_bench_help_says_what_unset_means(capsys, monkeypatch):
    from exploregs_plugin.scripts.bench import main

    text = _help(capsys, monkeypatch, lambda: main(["--help"]))
    assert "(default: None)" not in text and "(repeatable). (repeatable)" not in text
    assert "(default: the preset's or spec file's, else 1000)" in text
