"""Ablation experiment specs and the degraded (monocular-like) depth maps."""

from __future__ import annotations

import math

import pytest
import torch

from exploregs_plugin.data.depth_supervision import (
    N_WAVES, DepthSupervisionConfig, degrade_depth, smooth_field,
)
from exploregs_plugin.analysis.experiments import (
    BRANCH_ABLATION, DEPTH_SUPERVISION, EXPERIMENTS, METHOD_KEY, SPLIT_ABLATION, apply_overrides, entry_config,
)
from exploregs_plugin.pipeline import PipelineConfig
from exploregs_plugin.trainer import TrainerConfig

HAS_DEPTH_SUPERVISION = hasattr(PipelineConfig(), "depth_supervision")


def _resolvable(entry: dict) -> bool:
    return HAS_DEPTH_SUPERVISION or not any(k.startswith("pipeline.depth_supervision") for k in entry)


def test_branch_ablation_covers_every_subset_once():
    subsets = {tuple(e["pipeline.model.detach_paths"]) for e in BRANCH_ABLATION.values()}
    assert len(BRANCH_ABLATION) == 8 == len(subsets)
    assert () in subsets and ("mean2d", "cov", "sh") in subsets
    config = entry_config(BRANCH_ABLATION["no-cov"], data="builtin:tiny", max_steps=5)
    assert isinstance(config, TrainerConfig)
    assert config.pipeline.model.detach_paths == ("cov",) and config.max_steps == 5
    assert config.method_name == "exploregs-default"


def test_every_entry_builds_a_config_with_its_overrides():
    for name, (description, entries) in EXPERIMENTS.items():
        assert description and entries, name
        for entry_name, entry in entries.items():
            if not _resolvable(entry):
                continue
            config = entry_config(entry)
            assert config.method_name == entry[METHOD_KEY]
            for dotted, value in entry.items():
                if dotted == METHOD_KEY:
                    continue
                obj = config
                for part in dotted.split("."):
                    obj = getattr(obj, part)
                assert obj == value, (name, entry_name, dotted)


def test_depth_and_split_entries():
    assert {"default", "default+depth", "seed", "seed+depth", "seedsplit", "seedsplit+depth"} <= set(DEPTH_SUPERVISION)
    assert DEPTH_SUPERVISION["seed+depth"]["pipeline.depth_loss_weight"] > 0
    assert "pipeline.depth_loss_weight" not in DEPTH_SUPERVISION["seed"]
    n_splits = sorted(e["pipeline.strategy.n_split"] for e in SPLIT_ABLATION.values() if "pipeline.strategy.n_split" in e)
    assert n_splits[0] == 0 and len(n_splits) >= 4
    assert entry_config(SPLIT_ABLATION["split-n40"]).pipeline.strategy.n_split == 40
    assert entry_config(SPLIT_ABLATION["default-grad0.0004"]).pipeline.strategy.grow_grad2d == 0.0004


def test_apply_overrides_errors_name_the_field():
    with pytest.raises(ValueError, match="no field 'nope'"):
        apply_overrides(TrainerConfig(), {"pipeline.nope": 1})
    with pytest.raises(ValueError, match="not a config"):
        apply_overrides(TrainerConfig(), {"max_steps.x": 1})
    with pytest.raises(ValueError, match="names no"):
        entry_config({"max_steps": 3})
    base = TrainerConfig()
    changed = apply_overrides(base, {"pipeline.ssim_lambda": 0.5, "max_steps": 9})
    assert changed.pipeline.ssim_lambda == 0.5 and changed.max_steps == 9
    assert base.pipeline.ssim_lambda == 0.2  # the original is untouched


def test_degraded_depth_statistics_and_determinism():
    h, w = 96, 128
    depth = torch.full((h, w, 1), 4.0)
    depth[0, 0, 0] = 0.0  # invalid pixels stay as they are
    depth[1, 0, 0] = float("inf")
    noise_only = degrade_depth(depth, 3, DepthSupervisionConfig(noise_std=0.05, seed=1))
    rel = noise_only[2:] / 4.0 - 1.0
    assert rel.std().item() == pytest.approx(0.05, rel=0.1) and abs(rel.mean().item()) < 0.005
    assert noise_only[0, 0, 0] == 0.0 and math.isinf(noise_only[1, 0, 0].item())
    bias_only = degrade_depth(depth, 3, DepthSupervisionConfig(bias_amplitude=0.1, seed=1))
    brel = bias_only[2:, :, 0] / 4.0 - 1.0
    # smooth: a pixel step changes the bias by at most b N k / sqrt(N / 2) (N waves, k = 2 pi / wavelength)
    bound = 0.1 * N_WAVES * (2 * math.pi / (0.5 * w)) / math.sqrt(N_WAVES / 2)
    assert (brel[:, 1:] - brel[:, :-1]).abs().max() <= bound and brel.abs().max() > 0.05
    again = degrade_depth(depth, 3, DepthSupervisionConfig(bias_amplitude=0.1, seed=1))
    other_view = degrade_depth(depth, 4, DepthSupervisionConfig(bias_amplitude=0.1, seed=1))
    assert torch.equal(again, bias_only) and not torch.equal(other_view, bias_only)
    assert (degrade_depth(depth, 0, DepthSupervisionConfig(noise_std=5.0))[2:] > 0).all()
    plain = DepthSupervisionConfig()
    assert not plain.active and plain.apply(depth, 0) is depth


def test_smooth_field_has_unit_rms_and_bad_configs_fail():
    field = smooth_field(256, 256, 64.0, torch.Generator().manual_seed(0))
    assert field.pow(2).mean().sqrt().item() == pytest.approx(1.0, rel=0.35)
    with pytest.raises(ValueError, match="noise_std"):
        DepthSupervisionConfig(noise_std=-1.0)
    with pytest.raises(ValueError, match="bias_wavelength"):
        DepthSupervisionConfig(bias_wavelength=0.0)
    with pytest.raises(ValueError, match=r"\[H, W, 1\]"):
        degrade_depth(torch.ones(4, 4), 0, DepthSupervisionConfig(noise_std=0.1))


def test_cli_overrides_parse_to_the_same_config_as_the_dotted_fields():
    import tyro

    from exploregs_plugin.analysis.experiments import cli_overrides
    from exploregs_plugin.method_configs import get_method

    assert cli_overrides(BRANCH_ABLATION["no-cov-sh"]) == ("--model.detach-paths", "cov", "sh")
    assert cli_overrides(BRANCH_ABLATION["all-branches"]) == ("--model.detach-paths",)
    assert cli_overrides(SPLIT_ABLATION["default-grad0.0004"]) == ("--strategy.grow-grad2d", "0.0004")
    for entry in (BRANCH_ABLATION["all-branches"], BRANCH_ABLATION["no-mean2d-sh"], DEPTH_SUPERVISION["seed+depth"],
                  SPLIT_ABLATION["split-n40"]):  # fmt: skip
        base = get_method(entry[METHOD_KEY]).config
        parsed = tyro.cli(type(base), args=list(cli_overrides(entry)), default=base)
        assert parsed == entry_config(entry), entry
