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
from exploregs_plugin.strategies.synthetic import make_gaussians, make_optimizers, synthetic_info


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


def test_entry_point_strategy_is_discovered(tmp_path, monkeypatch):
    _fake_distribution(
        tmp_path,
        "eg_fake_plugin",
        "fancy = eg_fake_plugin_mod:FancyStrategy",
        """
        from dataclasses import dataclass
        import torch
        from exploregs_plugin.strategies import DefaultStrategy, StepContext, ops

        @dataclass
        class FancyStrategy(DefaultStrategy):
            fanciness: float = 2.0

            def explore(self, ctx: StepContext) -> dict[str, int]:
                counts = super().explore(ctx)
                n = ctx.params["means"].shape[0]
                mask = torch.zeros(n, dtype=torch.bool)
                mask[0] = True
                counts["fancy"] = ops.duplicate(ctx.params, ctx.optimizers, ctx.state["stats"], mask)
                return counts
        """,
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    names = available_strategies()
    assert names["fancy"].__name__ == "FancyStrategy"
    strategy = names["fancy"](refine_start_iter=0, refine_stop_iter=10, refine_every=5, reset_every=100)
    assert strategy.fanciness == 2.0
    g = torch.Generator().manual_seed(0)
    params = make_gaussians(4, g)
    info = synthetic_info(torch.zeros(4, 2), torch.ones(4, dtype=torch.bool), 8, 8)
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
