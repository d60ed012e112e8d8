"""The operator contract: a composed strategy runs its operators in the order of their fields, at
the points of Default's step the hooks name, and merges what they return."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, ClassVar

import pytest
import torch

from exploregs_plugin.schedule import ScheduleConfig
from exploregs_plugin.strategies import ExplorationStrategy, Operator, RandomSeeding, RandomSplitting, StrategyError
from exploregs_plugin.strategies.synthetic import make_gaussians, make_optimizers, synthetic_views

WINDOW = dict(refine_start_iter=2, refine_stop_iter=500, refine_every=10, reset_every=100)


@dataclass
class Recorder(Operator):
    """Writes each hook call into ``state["calls"]``; prunes row ``prune_row`` at refinements and
    asks for ``size_factor`` as the world-size threshold."""

    COUNTS: ClassVar[tuple[str, ...]] = ("recorded",)
    BUDGET_FIELDS: ClassVar[dict[str, str]] = {"every": "seed_every"}

    tag: str = "a"
    size_factor: float | None = None
    prune_row: int | None = None
    every: int | None = None
    """Budget-filled like Seeding's interval: None until setup."""

    def observe(self, owner: Any, params: Any, state: dict[str, Any], view: Any) -> dict[str, int]:
        state.setdefault("calls", []).append(("observe", self.tag))
        return {"observed": 1}

    def size_prune_factor(self, owner: Any, step: int) -> float | None:
        return self.size_factor

    def extra_prune(self, owner: Any, params: Any, state: dict[str, Any], step: int):
        state.setdefault("calls", []).append(("prune", self.tag))
        if self.prune_row is None:
            return None, {}
        mask = torch.zeros(params["means"].shape[0], dtype=torch.bool)
        mask[self.prune_row] = True
        return mask, {"recorder_pruned": 1}

    def explore(self, owner: Any, ctx: Any) -> dict[str, int]:
        ctx.state.setdefault("calls", []).append(("explore", self.tag))
        return {"recorded": 1} if ctx.step % 2 == 0 else {}

    def exploration_summary(self, state: dict[str, Any]) -> dict[str, int]:
        return {f"summary_{self.tag}": len(state.get("calls", []))}


@dataclass
class TwoRecorders(ExplorationStrategy):
    second: Recorder = field(default_factory=lambda: Recorder("b", size_factor=7.0, prune_row=3))
    first: Recorder = field(default_factory=lambda: Recorder("a", size_factor=None, prune_row=5))


def _step(strategy, params, optimizers, state, step):
    n = params["means"].shape[0]
    views = synthetic_views(torch.zeros(n, 2), torch.ones(n, dtype=torch.bool), 32, 32)
    return strategy.step_post_backward(params, optimizers, state, step, views, generator=torch.Generator().manual_seed(0))


def test_operators_run_in_field_order_at_their_hooks_and_merge_what_they_return():
    s = TwoRecorders(grow_grad2d=1e9, prune_opa=0.0, **WINDOW).setup(ScheduleConfig().resolve(1000))
    assert [name for name, _ in s.operators()] == ["second", "first"]  # field order, not name order
    assert s.second.every == s.first.every == s.refine_every  # the paper budget's seeding interval
    params = make_gaussians(10, torch.Generator().manual_seed(0))
    optimizers = make_optimizers(params)
    state = s.initialize_state()
    counts = _step(s, params, optimizers, state, 3)  # not a refinement step, odd: nothing to report
    assert state["calls"] == [("observe", "b"), ("observe", "a"), ("explore", "b"), ("explore", "a")]
    assert counts["observed"] == 2 and counts["recorded"] == 0  # summed; COUNTS filled with 0
    state["calls"] = []
    counts = _step(s, params, optimizers, state, 10)  # a refinement: both prunes OR-ed, then explore
    assert state["calls"] == [("observe", "b"), ("observe", "a"), ("prune", "b"), ("prune", "a"),
                              ("explore", "b"), ("explore", "a")]
    assert counts["recorder_pruned"] == 2 and counts["pruned"] == 2 and counts["recorded"] == 2
    assert params["means"].shape[0] == 8
    # the first operator with an opinion sets the world-size threshold; Default's without one
    assert s.size_prune_factor(200) == 7.0
    assert TwoRecorders(second=Recorder("b"), first=Recorder("a"), **WINDOW).size_prune_factor(200) == 0.1
    assert s.exploration_summary(state) == {"summary_b": 6, "summary_a": 6}


def test_setup_fills_operators_without_touching_the_given_config_and_names_what_is_unset():
    given = TwoRecorders(**WINDOW)
    ready = given.setup(ScheduleConfig().resolve(1000))
    assert given.second.every is None and ready.second.every is not None
    assert ready.second is not given.second
    with pytest.raises(StrategyError, match=r"second\.every"):
        _step(given, make_gaussians(4, torch.Generator()), make_optimizers(make_gaussians(4, torch.Generator())),
              given.initialize_state(), 3)


def test_reversed_operators_run_reversed():
    # Seed+Split splits first, so fresh seeds are not split in their step; the reverse order, made
    # by declaring the fields the other way round, seeds first and may split a seed at once
    @dataclass
    class SeedThenSplit(ExplorationStrategy):
        seeding: RandomSeeding = field(default_factory=lambda: RandomSeeding(n_seed=5, every=10))
        splitting: RandomSplitting = field(default_factory=lambda: RandomSplitting(n_split=40, every=1))

    s = SeedThenSplit(grow_grad2d=1e9, prune_opa=0.0, **WINDOW)
    params = make_gaussians(10, torch.Generator().manual_seed(0))
    optimizers = make_optimizers(params)
    state = s.initialize_state()
    counts = _step(s, params, optimizers, state, 10)
    # 5 seeds join the 10 rows, then all 15 are split (40 asked for, 15 exist): the seeds too
    assert counts["seeded"] == 5 and counts["random_split"] == 15
    assert params["means"].shape[0] == 30
    assert int(state["stats"]["seed"].sum()) == 10  # each seed's two children keep its flag


@pytest.mark.parametrize("field, value", [("lr", -1.0), ("lr", float("nan")), ("gate_k", 0.0), ("gate_t", 1.5)])
def test_position_noise_refuses_a_bad_scale_or_gate(field, value):
    from exploregs_plugin.strategies.position_noise import PositionNoise

    with pytest.raises(StrategyError, match=f"noise {field}"):
        PositionNoise(**{field: value})
