"""available_strategies(): built-ins plus entry points in group exploregs.strategies."""

from __future__ import annotations

import textwrap

import pytest
import torch

from exploregs_plugin.strategies import (
    ENTRY_POINT_GROUP,
    DefaultStrategy,
    Strategy,
    StrategyPluginError,
    available_strategies,
)
from exploregs_plugin.strategies.synthetic import make_gaussians, make_optimizers, synthetic_views


def _fake_distribution(root, name: str, entry_points: str, module_source: str | None = None):
    """A minimal installed distribution (dist-info with entry_points.txt) under ``root``."""
    info = root / f"{name}-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {name}\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text(f"[{ENTRY_POINT_GROUP}]\n{entry_points}\n")
    if module_source is not None:
        (root / f"{name}_mod.py").write_text(textwrap.dedent(module_source))


def test_builtins_are_listed():
    names = available_strategies()
    assert {"default", "seed", "split", "seedsplit", "ray", "mcmc"} <= set(names)
    assert names["default"] is DefaultStrategy
    assert all(issubclass(cls, Strategy) for cls in names.values())


FANCY_SOURCE = """
from dataclasses import dataclass
import torch
from exploregs_plugin.strategies import DefaultStrategy, StepContext, row_ops

@dataclass
class FancyStrategy(DefaultStrategy):
    fanciness: float = 2.0

    def explore(self, ctx: StepContext) -> dict[str, int]:
        counts = super().explore(ctx)
        n = ctx.params["means"].shape[0]
        mask = torch.zeros(n, dtype=torch.bool)
        mask[0] = True
        counts["fancy"] = row_ops.duplicate(ctx.params, ctx.optimizers, ctx.state["stats"], mask)
        return counts
"""


def _fancy_plugin(tmp_path, monkeypatch) -> None:
    _fake_distribution(tmp_path, "eg_fake_plugin", "fancy = eg_fake_plugin_mod:FancyStrategy", FANCY_SOURCE)
    monkeypatch.syspath_prepend(str(tmp_path))


def test_entry_point_strategy_is_discovered(tmp_path, monkeypatch):
    _fancy_plugin(tmp_path, monkeypatch)
    names = available_strategies()
    assert names["fancy"].__name__ == "FancyStrategy"
    strategy = names["fancy"](refine_start_iter=0, refine_stop_iter=10, refine_every=5, reset_every=100)
    assert strategy.fanciness == 2.0
    g = torch.Generator().manual_seed(0)
    params = make_gaussians(4, g)
    info = synthetic_views(torch.zeros(4, 2), torch.ones(4, dtype=torch.bool), 8, 8)
    counts = strategy.step_post_backward(params, make_optimizers(params), strategy.initialize_state(), 1, info)
    assert counts["fancy"] == 1 and params["means"].shape[0] == 5


@pytest.mark.parametrize(
    "line, module, message",
    [
        ("broken = eg_missing_module_xyz:Thing", None, "failed to load: ModuleNotFoundError"),
        ("broken = eg_bad_plugin_mod:Thing", "raise RuntimeError('boom')\n", "failed to load: RuntimeError: boom"),
        ("broken = eg_bad_plugin_mod:VALUE", "VALUE = 3\n", "not a strategy class"),
        ("default = eg_bad_plugin_mod:VALUE", "VALUE = 3\n", "reuses the strategy name 'default'"),
    ],
)
def test_broken_entry_point_is_a_clear_error(tmp_path, monkeypatch, line, module, message):
    _fake_distribution(tmp_path, "eg_bad_plugin", line, module)
    monkeypatch.syspath_prepend(str(tmp_path))
    with pytest.raises(StrategyPluginError) as err:
        available_strategies()
    text = str(err.value)
    assert message in text
    assert "eg_bad_plugin" in text and ENTRY_POINT_GROUP in text


def test_a_plugin_strategy_is_selectable_with_every_method(tmp_path, monkeypatch):
    from exploregs_plugin.method_configs import all_methods
    from exploregs_plugin.scripts.train import parse_config

    _fancy_plugin(tmp_path, monkeypatch)
    for name, spec in all_methods().items():
        config = parse_config([name, "--strategy", "fancy", "--strategy.fanciness", "3", "--max-steps", "7"])
        strategy = config.pipeline.strategy
        assert type(strategy).__name__ == "FancyStrategy" and strategy.fanciness == 3.0, name
        # the rest of the method stays: its model, data, schedule
        assert type(config.pipeline.model) is type(spec.config.pipeline.model), name
        assert config.pipeline.datamanager.data == spec.config.pipeline.datamanager.data, name
        assert config.method_name == name and config.max_steps == 7


@pytest.mark.parametrize("method", ["exploregs-seedsplit", "exploregs-4d-default"])
def test_a_plugin_strategy_trains_inside_a_built_in_method(tmp_path, monkeypatch, tiny_scene_dir, method):
    from exploregs_plugin.scripts.train import parse_config

    _fancy_plugin(tmp_path, monkeypatch)
    config = parse_config([method, "--strategy=fancy", "--data", "builtin:tiny", "--max-steps", "6", "--run-dir",
                           str(tmp_path / "run"), "--quiet", "--no-tensorboard", "--eval-count", "1",
                           "--no-save-eval-images", "--num-threads", "1"])
    trainer = config.setup()
    start = trainer.pipeline.model.num_gaussians
    trainer.train()
    # its operator ran at every step (one duplicate each), nothing else grew the set so early, and
    # the end-of-run cut (Default's, which the plugin inherits) is in the run's totals
    assert trainer.op_totals["fancy"] == 6
    assert trainer.pipeline.model.num_gaussians == start + 6 - trainer.op_totals.get("pruned", 0)


def test_built_in_names_select_the_named_methods_strategy_and_bad_names_are_one_line(capsys):
    from exploregs_plugin.method_configs import get_method
    from exploregs_plugin.scripts.train import parse_config

    config = parse_config(["exploregs-default", "--strategy", "seedsplit"])
    assert config.pipeline.strategy == get_method("exploregs-seedsplit").config.pipeline.strategy
    assert config.method_name == "exploregs-default"
    from exploregs_plugin.strategies.registry import available_strategies

    names = sorted(available_strategies())
    assert {"default", "seedsplit", "mcmc", "gsplat-default", "gsplat-mcmc"} <= set(names)  # built in and entry points
    for argv, expected in ((["exploregs-default", "--strategy", "nope"], "unknown strategy 'nope'; registered "
                            f"strategies: {', '.join(names)}"),
                           (["exploregs-default", "--strategy"], "--strategy needs the name of a registered strategy"),
                           (["--strategy", "seed"], "--strategy NAME needs a method first")):
        with pytest.raises(SystemExit) as exit_:
            parse_config(argv)
        assert exit_.value.code == 2
        assert capsys.readouterr().err.strip().splitlines()[-1].startswith(f"eg-train: error: {expected}")


def test_strategies_declare_what_they_need_and_the_renderer_computes_just_that():
    from exploregs_plugin.model import GaussianModelConfig
    from exploregs_plugin.engine.pipeline import renderer_for
    from exploregs_plugin.strategies import SeedSplitStrategy
    from exploregs_plugin.strategies.base import StrategyError
    from exploregs_plugin.strategies.operator_contract import Operator
    from exploregs_plugin.strategies.requirements import VIEW_ERRORS, VISIBILITY_STATS
    from exploregs_plugin.strategies.guided import GuidedSeedingStrategy
    from exploregs_plugin.strategies.occlusion import GuidedOcclusionStrategy, OcclusionSplittingStrategy

    # a composed strategy requires what each of its operators does
    assert GuidedOcclusionStrategy().requirements() == {VIEW_ERRORS, VISIBILITY_STATS}
    assert OcclusionSplittingStrategy().requirements() == {VISIBILITY_STATS}
    assert GuidedSeedingStrategy().requirements() == {VIEW_ERRORS} and SeedSplitStrategy().requirements() == frozenset()
    model = GaussianModelConfig()
    assert renderer_for(model, OcclusionSplittingStrategy().requirements()).raster.visibility_stats
    plain = renderer_for(model, GuidedSeedingStrategy().requirements())
    assert plain is model and not model.raster.visibility_stats
    for base in (DefaultStrategy, Operator):
        with pytest.raises(StrategyError, match="requires names"):
            type("Odd", (base,), {"requires": frozenset({"depth"})})
