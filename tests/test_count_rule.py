"""The count decided on held-out views (MCMC's ``cap_max 'validated'``): the rule's pure parts, the
strategy's windows and stop, and a run on the tiny scene (views held out until the decision,
deterministic, resumed with the same decision)."""

from __future__ import annotations

import math
import shutil
from dataclasses import replace

import pytest
import torch

from exploregs_plugin.callbacks import TrainingCallback
from exploregs_plugin.method_configs import get_method
from exploregs_plugin.schedule import ScheduleConfig
from exploregs_plugin.strategies import MCMCStrategy, StrategyError
from exploregs_plugin.strategies.count_rule import (growth_contrast, growth_paid, held_out_count, held_out_indices,
                                                    reading_due, window_grows)
from exploregs_plugin.strategies.synthetic import adam_steps, make_gaussians, make_optimizers, synthetic_views
from exploregs_plugin.trainer import Trainer

WINDOW = dict(refine_start_iter=2, refine_stop_iter=1000, refine_every=10, reset_every=100)


# ------------------------------------------------------------------------------ the rule
def test_held_out_views_are_spread_over_the_capture_and_few():
    assert [held_out_count(n) for n in (3, 7, 8, 24, 36, 71, 96, 400)] == [0, 0, 2, 2, 3, 5, 8, 8]
    assert held_out_indices(7) == []
    assert held_out_indices(8) == [2, 6]
    assert held_out_indices(62) == [6, 18, 31, 43, 55]
    for n in (8, 13, 62, 250):
        idx = held_out_indices(n)
        gaps = [b - a for a, b in zip(idx, idx[1:])]
        assert len(set(idx)) == len(idx) and 0 <= idx[0] and idx[-1] < n
        assert max(gaps) - min(gaps) <= 1  # evenly spread


def test_windows_alternate_hold_first_and_are_read_at_their_start():
    assert [window_grows(k, 3) for k in range(9)] == [False] * 3 + [True] * 3 + [False] * 3
    assert [reading_due(k, 3) for k in range(7)] == [True, False, False, True, False, False, True]


def test_the_contrast_is_a_grow_windows_gain_beyond_the_mean_of_the_holds_around_it():
    # gains: hold 2.0, grow 1.5, hold 0.5 -> 1.5 - (2.0 + 0.5) / 2 = 0.25
    assert growth_contrast([10.0, 12.0, 13.5, 14.0]) == pytest.approx(0.25)
    # due only when a hold window after a grow window closes: m = 3, 5, 7, ...
    assert [growth_contrast([0.0] * k) for k in (1, 2, 3, 5)] == [None] * 4
    assert growth_contrast([10.0, 12.0, 13.5, 14.0, 15.0]) is None
    # m = 5: grow window 3 (14.0 -> 14.2) between holds 13.5 -> 14.0 and 14.2 -> 14.3
    assert growth_contrast([10.0, 12.0, 13.5, 14.0, 14.2, 14.3]) == pytest.approx(0.2 - 0.5 * (0.5 + 0.1))
    # training alone rising linearly: growth that adds nothing has contrast 0 whatever the slope
    for slope in (0.0, 0.3, 2.0):
        assert growth_contrast([20.0 + slope * j for j in range(8)]) == pytest.approx(0.0, abs=1e-12)
    assert growth_paid(0.05, 0.05) and not growth_paid(0.049, 0.05)
    assert not growth_paid(float("nan"), 0.0) and not growth_paid(float("inf") * 0, 0.05)
    assert math.isnan(growth_contrast([10.0, float("nan"), 11.0, 12.0]))


# ------------------------------------------------------------------------------ the strategy
def _set(n: int, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    params = make_gaussians(n, g)
    with torch.no_grad():
        params["opacities"].copy_(torch.logit(0.2 + 0.7 * torch.rand(n, generator=g)))
    optimizers = make_optimizers(params)
    adam_steps(params, optimizers, g)
    return params, optimizers


def _run(strategy, psnr_of, steps=400):
    """``steps`` synthetic steps of ``strategy``; the held-out PSNR is ``psnr_of(step, count)``.
    Returns (count after each step, steps at which the PSNR was read, the state)."""
    params, optimizers = _set(100)
    state = strategy.initialize_state()
    counts, reads = {}, []

    def score(step):
        reads.append(step)
        return psnr_of(step, params["means"].shape[0])

    for step in range(3, steps):
        views = synthetic_views(torch.zeros(params["means"].shape[0], 2),
                                torch.ones(params["means"].shape[0], dtype=torch.bool), 32, 32,
                                torch.tensor([0.0, 0.0, -3.0]))
        held = strategy.holds_out_views(state, step)
        strategy.step_post_backward(params, optimizers, state, step, views, lr=1.6e-4,
                                    generator=torch.Generator().manual_seed(step),
                                    held_out_psnr=(lambda s=step: score(s)) if held else None)
        counts[step] = params["means"].shape[0]
    return counts, reads, state


def test_growth_happens_only_in_grow_windows_and_stops_where_it_stops_paying():
    """Refinements every 10 steps from step 10 (index 0), windows of 2: holds at indices 0-1,
    4-5, ..., growth at 2-3, 6-7, ... The held-out PSNR rises with training (0.002 dB a step) and
    with 4 ln(count) up to 130 Gaussians, flat beyond: the windows that grow from 100 to 110, 110
    to 120 and 120 to 132 pay (0.38, 0.35 and 0.32 dB beyond training); the one from 132 to 144
    adds nothing beyond training and stops growth at its end, 144: one window past the count the
    scene needs, 11% above it."""
    strategy = MCMCStrategy(cap_max="validated", count_window=2, count_min_gain=0.05, **WINDOW)

    def psnr(step, n):
        return 20.0 + 0.002 * step + 4.0 * math.log(min(n, 130) / 100.0)

    counts, reads, state = _run(strategy, psnr)
    assert reads == list(range(10, 300, 20))[: len(reads)] and reads[0] == 10
    grown = [s for s in counts if s > 3 and counts[s] > counts[s - 1]]
    assert grown == [30, 40, 70, 80, 110, 120, 150, 160]  # the grow windows' refinements only
    assert [counts[s] for s in grown] == [105, 110, 115, 120, 126, 132, 138, 144]
    cap = state["count_cap"]
    assert cap == 144 and all(counts[s] == cap for s in range(160, 400))
    contrasts = state["count_contrasts"]
    assert [n for n, _ in contrasts] == [110, 120, 132, 144]
    assert all(c >= 0.05 for _, c in contrasts[:-1]) and contrasts[-1][1] < 0.05
    assert not strategy.holds_out_views(state, 200)
    assert strategy.exploration_summary(state) == {"auto_cap": 144}
    assert "growth stopped at 144 Gaussians" in strategy.count_decision(state)


def test_a_count_that_never_pays_stops_after_one_grow_window():
    strategy = MCMCStrategy(cap_max="validated", count_window=3, count_min_gain=0.05, **WINDOW)
    counts, _, state = _run(strategy, lambda step, n: 25.0 - 0.001 * step, steps=200)
    assert state["count_cap"] == 115 and max(counts.values()) == 115  # 100 -> 105 -> 110 -> 115, no more


def test_the_rule_needs_the_held_out_score_and_a_sane_window():
    strategy = MCMCStrategy(cap_max="validated", **WINDOW)
    params, optimizers = _set(20)
    views = synthetic_views(torch.zeros(20, 2), torch.ones(20, dtype=torch.bool), 32, 32, torch.tensor([0.0, 0.0, -3.0]))
    with pytest.raises(StrategyError, match="held_out_psnr="):
        strategy.step_post_backward(params, optimizers, strategy.initialize_state(), 10, views, lr=1e-4,
                                    generator=torch.Generator().manual_seed(0))
    for bad in (dict(count_window=0), dict(count_min_gain=-0.1), dict(count_min_gain=float("nan"))):
        with pytest.raises(StrategyError, match="count_window"):
            MCMCStrategy(cap_max="validated", **WINDOW, **bad)
    with pytest.raises(StrategyError, match="validated"):
        MCMCStrategy(cap_max="validate", **WINDOW)


# ------------------------------------------------------------------------------ a run
class _Record(TrainingCallback):
    def __init__(self):
        self.views, self.counts, self.held = {}, {}, {}

    def after_step(self, trainer, step, stats):
        self.views[step] = stats["views"]
        self.counts[step] = trainer.pipeline.model.num_gaussians
        self.held[step] = trainer.pipeline.datamanager.held_out


def _config(run_dir, **strategy_fields):
    config = get_method("exploregs-mcmc").config
    strategy = replace(config.pipeline.strategy, cap_max="validated", count_window=2, **strategy_fields)
    return replace(config, data="builtin:tiny", max_steps=300, run_dir=run_dir, quiet=True, tensorboard=False,
                   eval_count=1, save_eval_images=False, checkpoint_every=100,
                   schedule=ScheduleConfig(min_refine_every=10), pipeline=replace(config.pipeline, strategy=strategy))


def test_a_run_holds_views_out_until_the_decision_and_resumes_with_it(tmp_path, tiny_scene_dir):
    """The tiny scene (8 training views; 2 held out), refinements every 10 steps until step 250,
    windows of 2. A gain no window can reach (1000 dB) stops growth at the first decision, after
    hold, grow, hold (index 6, step 70): the count of one grow window. The held-out views are not
    drawn before then and are drawn after; a second run gives the same bits, and a run resumed from
    step 100 (after the decision) keeps it."""
    record = _Record()
    trainer = _config(tmp_path / "run", count_min_gain=1000.0).setup(callbacks=[record])
    n0 = trainer.pipeline.model.num_gaussians
    held = trainer.pipeline.datamanager.held_out
    assert held == [2, 6]
    m = trainer.train()
    returned = min(s for s, h in record.held.items() if not h)
    assert returned == 71  # the refinement at step 70 decided; the views return from step 71's draw on
    assert not {i for s in range(1, returned + 1) for i in record.views[s]} & set(held)
    assert set(held) <= {i for s in range(returned + 1, 301) for i in record.views[s]}
    cap = m["exploration"]["auto_cap"]
    assert cap == record.counts[70] == m["num_gaussians"] > n0
    assert cap == int(1.05 * int(1.05 * n0))  # two growths (steps 30 and 40), none after
    assert m["count_decision"].startswith(f"growth stopped at {cap:,} Gaussians (step 70)")
    state = trainer.pipeline.strategy_state
    assert len(state["count_readings"]) == 4 and all(math.isfinite(p) for p in state["count_readings"])

    again = _config(tmp_path / "again", count_min_gain=1000.0).setup()
    again.train()
    for name, p in trainer.pipeline.params.items():
        assert torch.equal(p, again.pipeline.params[name]), name

    resumed_dir = tmp_path / "resumed"
    shutil.copytree(tmp_path / "run", resumed_dir)
    for late in sorted((resumed_dir / "checkpoints").glob("*.pt"))[1:]:
        late.unlink()  # keep step-0000100.pt
    resumed = Trainer.from_run(resumed_dir, max_steps=None, quiet=True)
    assert resumed.pipeline.datamanager.held_out == [] and resumed.pipeline.strategy_state["count_cap"] == cap
    resumed.train()
    for name, p in trainer.pipeline.params.items():
        assert torch.equal(p, resumed.pipeline.params[name]), name


def test_a_run_resumed_before_the_decision_holds_the_same_views_and_decides_alike(tmp_path, tiny_scene_dir):
    config = _config(tmp_path / "run", count_min_gain=1000.0)
    config = replace(config, checkpoint_every=50, keep_checkpoints=10)
    trainer = config.setup()
    m = trainer.train()
    resumed_dir = tmp_path / "resumed"
    shutil.copytree(tmp_path / "run", resumed_dir)
    for late in sorted((resumed_dir / "checkpoints").glob("*.pt"))[1:]:
        late.unlink()  # keep step-0000050.pt: two readings, before the decision at 70
    resumed = Trainer.from_run(resumed_dir, max_steps=None, quiet=True)
    assert resumed.start_step == 50 and resumed.pipeline.datamanager.held_out == [2, 6]
    assert resumed.pipeline.strategy_state["count_cap"] is None
    r = resumed.train()
    assert r["exploration"]["auto_cap"] == m["exploration"]["auto_cap"]
    for name, p in trainer.pipeline.params.items():
        assert torch.equal(p, resumed.pipeline.params[name]), name


def test_too_few_training_views_to_hold_out_is_one_clear_line(tmp_path, tiny_scene_dir):
    config = _config(tmp_path / "run")
    config = replace(config, pipeline=replace(config.pipeline, datamanager=replace(
        config.pipeline.datamanager, test_every=2, use_dataset_split=False)))  # 5 training views of 10
    with pytest.raises(ValueError, match="at least 8 training views"):
        config.setup()


def test_the_datamanager_passes_over_held_views_and_keeps_them_in_its_state(tiny_dm):
    """Held views are never drawn, the order of the others is the seeded one with them left out,
    the held list travels in the state, and a bad list is refused."""
    from exploregs_plugin.data import DataManagerConfig

    plain = DataManagerConfig(data="builtin:tiny").setup()
    expected = [i for i in plain.next_train_indices(40) if i not in (1, 5)]
    tiny_dm.hold_out([5, 1])
    assert tiny_dm.held_out == [1, 5]
    drawn = tiny_dm.next_train_indices(len(expected))
    assert drawn == expected  # the same permutations, the held ones passed over
    state = tiny_dm.state_dict()
    again = DataManagerConfig(data="builtin:tiny").setup()
    again.load_state_dict(state)
    assert again.held_out == [1, 5] and again.next_train_indices(12) == tiny_dm.next_train_indices(12)
    tiny_dm.return_held()
    assert {1, 5} <= set(tiny_dm.next_train_indices(16))  # two epochs: every view again
    for bad in ([8], [-1], list(range(8))):
        with pytest.raises(ValueError, match="hold_out"):
            tiny_dm.hold_out(bad)
    del state["held_out"]  # a checkpoint from before held-out views holds none
    again.load_state_dict(state)
    assert again.held_out == []


def test_mcmc_explore_decides_its_count_the_same_way():
    from exploregs_plugin.strategies import MCMCExploreStrategy

    strategy = MCMCExploreStrategy(cap_max="validated", count_window=3, count_min_gain=0.05, explore_share=0.5,
                                   explore_split=1.0, explore_box=0.0, explore_guided=0.0, **WINDOW)
    counts, reads, state = _run(strategy, lambda step, n: 25.0 - 0.001 * step, steps=200)
    assert reads == [10, 40, 70, 100] and state["count_cap"] == 115 and max(counts.values()) == 115
