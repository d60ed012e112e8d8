"""The ablation experiments: every entry parses with eg-train's own parser to the config it names."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest

from exploregs_plugin.analysis.ablations import BRANCH_ABLATION, DEPTH_SUPERVISION, EXPERIMENTS, SPLIT_ABLATION
from exploregs_plugin.bench.spec import BenchEntry, BenchScene, BenchSpec, BenchSpecError, build_config, parse_overrides
from exploregs_plugin.method_configs import get_method
from exploregs_plugin.engine.trainer import TrainerConfig


def _by_name(entries):
    return {e.name: e for e in entries}


_BUILT: dict[tuple, TrainerConfig] = {}


def _config(run, tmp_path: Path) -> TrainerConfig:
    """The config eg-bench builds for the entry. Built once per entry for the module (tyro parses an
    entry's overrides in a few tenths of a second, and the three experiment tests share 27 entries);
    the key is all an entry is made of, and the run folder is no part of what the tests read."""
    key = (run.name, run.method, tuple(run.overrides), run.description)
    if key not in _BUILT:
        entry = BenchEntry(run.name, run.method, run.overrides, run.description)  # as the ablation presets make it
        spec = BenchSpec(entries=(entry,), scenes=(BenchScene("tiny", "builtin:tiny"),), steps=5)
        _BUILT[key] = build_config(spec, spec.scenes[0], entry, 0, tmp_path)
    return _BUILT[key]


def test_branch_ablation_covers_every_subset_once(tmp_path):
    configs = {name: _config(e, tmp_path) for name, e in _by_name(BRANCH_ABLATION).items()}
    subsets = {c.pipeline.model.detach_paths for c in configs.values()}
    assert len(BRANCH_ABLATION) == 8 == len(subsets)
    assert () in subsets and ("mean2d", "cov", "sh") in subsets
    assert BRANCH_ABLATION[0].name == "all-branches"
    no_cov = configs["no-cov"]
    assert no_cov.pipeline.model.detach_paths == ("cov",) and no_cov.max_steps == 5
    assert no_cov.method_name == "exploregs-branch-ablation"
    # the variant is Default with only its model's render changed: the same strategy and schedule
    from exploregs_plugin.method_configs import get_method

    default = get_method("exploregs-default").config
    assert no_cov.pipeline.strategy == default.pipeline.strategy and no_cov.schedule == default.schedule


def test_every_entry_builds_the_config_of_its_method(tmp_path):
    for name, entries in EXPERIMENTS.items():
        assert entries and len({e.name for e in entries}) == len(entries), name
        for entry in entries:
            config = _config(entry, tmp_path)
            assert config.method_name == entry.method, (name, entry.name)
            # an entry without overrides is its method's config, up to the bench's own fields
            if not entry.overrides:
                base = get_method(entry.method).config.pipeline
                assert replace(config.pipeline, datamanager=base.datamanager) == base


def test_depth_and_split_entries(tmp_path):
    depth = {n: _config(e, tmp_path).pipeline for n, e in _by_name(DEPTH_SUPERVISION).items()}
    assert {"default", "default+depth", "seed", "seed+depth", "seedsplit", "seedsplit+depth"} <= set(depth)
    assert depth["seed+depth"].depth_loss_weight > 0 and depth["seed"].depth_loss_weight == 0
    mono = depth["seedsplit+mono-depth"]
    assert mono.depth_supervision.noise_std == 0.05 and mono.depth_supervision.bias_amplitude == 0.1
    assert mono.depth_loss_weight == depth["seedsplit+depth"].depth_loss_weight
    assert mono.strategy == depth["seedsplit+depth"].strategy  # the same strategy, picked with --strategy
    assert not hasattr(depth["seedsplit+depth"], "depth_supervision")  # the core pipeline has no degradation
    split = {n: _config(e, tmp_path).pipeline.strategy for n, e in _by_name(SPLIT_ABLATION).items()}
    n_splits = sorted(s.splitting.n_split for n, s in split.items() if n.startswith("split-"))
    assert n_splits[0] == 0 and len(n_splits) >= 4
    assert split["split-n40"].splitting.n_split == 40
    assert split["default-grad0.0004"].grow_grad2d == 0.0004


def test_overrides_that_eg_train_rejects_name_the_entry():
    base = TrainerConfig()
    with pytest.raises(BenchSpecError, match="entry 'x'.*--pipeline.nope"):
        parse_overrides(base, ["--pipeline.nope", "1"], "entry 'x'")
    changed = parse_overrides(base, ["--ssim-lambda", "0.5", "--max-steps", "9"], "entry 'y'")
    assert changed.pipeline.ssim_lambda == 0.5 and changed.max_steps == 9
    assert base.pipeline.ssim_lambda == 0.2  # the original is untouched
