"""MCMC with exploration (a share of relocation and growth explored) and MCMC's automatic cap."""

from __future__ import annotations

import copy
import math

import pytest
import torch

from exploregs_plugin.strategies import MCMCExploreStrategy, MCMCStrategy, StrategyError
from exploregs_plugin.strategies.mcmc import keeps_growing
from exploregs_plugin.strategies.mcmc_explore import apportion, explored_count
from exploregs_plugin.strategies.observation import ViewError
from exploregs_plugin.strategies.requirements import VIEW_ERRORS
from exploregs_plugin.strategies.seeding import SEED_FLAG
from exploregs_plugin.strategies.synthetic import adam_steps, make_gaussians, make_optimizers, synthetic_views

WINDOW = dict(refine_start_iter=2, refine_stop_iter=500, refine_every=10, reset_every=100)
SIZE = 32


def _views(n: int, seed: int = 0):
    """One observed view of the synthetic set, with the error map guided seeding reads: a camera
    3 units in front of the origin looking along +z, 32 x 32 pixels."""
    g = torch.Generator().manual_seed(seed)
    views = synthetic_views(torch.zeros(n, 2), torch.ones(n, dtype=torch.bool), SIZE, SIZE,
                            torch.tensor([0.0, 0.0, -3.0]))
    viewmat = torch.eye(4)
    viewmat[2, 3] = 3.0
    K = torch.tensor([[32.0, 0.0, 16.0], [0.0, 32.0, 16.0], [0.0, 0.0, 1.0]])
    views[0].error = ViewError(0, viewmat, K, torch.rand(SIZE, SIZE, 3, generator=g),
                               torch.rand(SIZE, SIZE, generator=g))
    return views


def _set(n: int, n_dead: int, seed: int = 0):
    """n synthetic Gaussians whose first n_dead are dead (opacity 0.001), the rest alive (0.2-0.9),
    with non-zero Adam moments."""
    g = torch.Generator().manual_seed(seed)
    params = make_gaussians(n, g)
    with torch.no_grad():
        alive = 0.2 + 0.7 * torch.rand(n, generator=g)
        alive[:n_dead] = 0.001
        params["opacities"].copy_(torch.logit(alive))
    optimizers = make_optimizers(params)
    adam_steps(params, optimizers, g)
    return params, optimizers


def _step(strategy, params, optimizers, state, step, seed, loss=None):
    return strategy.step_post_backward(params, optimizers, state, step, _views(params["means"].shape[0], step),
                                       lr=1.6e-4, generator=torch.Generator().manual_seed(seed), loss=loss)


# ------------------------------------------------------------------------------ the share
def test_explored_count_rounds_half_up_and_apportion_is_exact():
    assert [explored_count(n, 0.3) for n in (0, 1, 2, 5, 37, 100)] == [0, 0, 1, 2, 11, 30]
    assert explored_count(5, 0.5) == 3  # 2.5 rounds up
    assert apportion(10, (1.0, 1.0, 1.0)) == [4, 3, 3]  # the remainder goes to the earlier weight
    assert apportion(7, (0.0, 1.0, 3.0)) == [0, 2, 5]
    assert apportion(0, (1.0, 1.0, 1.0)) == [0, 0, 0] and apportion(5, (0.0, 0.0, 0.0)) == [0, 0, 0]
    for k in range(40):
        assert sum(apportion(k, (0.2, 0.5, 0.3))) == k


def _refinements(strategy):
    """300 synthetic Gaussians (40 dead) through five steps of ``strategy``, refinements among them,
    with a few more killed after each so that every relocation has work."""
    params, optimizers = _set(300, 40)
    state = strategy.initialize_state()
    for step in (9, 10, 11, 20, 30):
        _step(strategy, params, optimizers, state, step, seed=step)
        with torch.no_grad():
            params["opacities"][step: step + 5] = -8.0
    return params, optimizers


def test_share_zero_is_mcmc_bit_for_bit():
    """Relocation, growth and noise over several refinements: the same parameters and moments."""
    (p_mcmc, o_mcmc), (p_explore, o_explore) = (
        _refinements(MCMCStrategy(cap_max=400, **WINDOW)),
        _refinements(MCMCExploreStrategy(cap_max=400, explore_share=0.0, **WINDOW)))
    assert p_mcmc["means"].shape[0] > 300
    for name in p_mcmc:
        assert torch.equal(p_mcmc[name], p_explore[name]), name
        s_mcmc, s_explore = o_mcmc[name].state[p_mcmc[name]], o_explore[name].state[p_explore[name]]
        for moment in ("exp_avg", "exp_avg_sq"):
            assert torch.equal(s_mcmc[moment], s_explore[moment]), (name, moment)


def test_caps_below_the_starting_count_never_grow_and_give_the_same_run():
    """A cap does not remove Gaussians: every cap at or below the starting count is the same run,
    at the starting count (the cap sweep trains one of them, docs/bench.md)."""
    runs = [_refinements(MCMCExploreStrategy(cap_max=cap, **WINDOW))[0] for cap in (0, 150, 300)]
    assert all(p["means"].shape[0] == 300 for p in runs)
    assert not torch.equal(runs[0]["means"], _set(300, 40)[0]["means"])  # relocation and noise moved them
    for other in runs[1:]:
        for name in runs[0]:
            assert torch.equal(runs[0][name], other[name]), name


@pytest.mark.parametrize("share, n_dead", [(0.3, 37), (0.5, 5), (1.0, 12)])
def test_the_share_of_relocated_rows_becomes_seeds_at_the_stated_opacity(share, n_dead):
    strategy = MCMCExploreStrategy(cap_max=1000, growth_rate=0.0, explore_share=share, explore_split=0.0,
                                   explore_box=1.0, explore_guided=0.0, **WINDOW)
    params, optimizers = _set(200, n_dead)
    state = strategy.initialize_state()
    counts = _step(strategy, params, optimizers, state, 10, seed=1)
    k = round(share * n_dead + 1e-9)
    assert counts["relocated"] == n_dead and counts["explored"] == k and counts["added"] == 0
    assert params["means"].shape[0] == 200  # a relocation keeps the count
    seeds = state["stats"][SEED_FLAG] > 0
    assert int(seeds.sum()) == k
    assert torch.allclose(torch.sigmoid(params["opacities"].detach()[seeds]), torch.tensor(0.05), atol=1e-6)
    # the other dead rows were relocated onto live ones: none is left at the dead opacity
    assert float(torch.sigmoid(params["opacities"].detach()).min()) > 0.002
    assert all(optimizers[name].param_groups[0]["params"][0] is params[name] for name in params)
    assert strategy.exploration_summary(state)["seeds_alive"] == k


def test_the_share_of_growth_is_explored_by_splits_and_both_kinds_of_seeds():
    strategy = MCMCExploreStrategy(cap_max=1000, growth_rate=0.2, explore_share=0.5, explore_split=1.0,
                                   explore_box=1.0, explore_guided=1.0, **WINDOW)
    params, optimizers = _set(100, 0)
    state = strategy.initialize_state()
    _step(strategy, params, optimizers, state, 9, seed=0)  # not a refinement: stores the view's error map
    assert params["means"].shape[0] == 100 and 0 in state["views"]
    counts = _step(strategy, params, optimizers, state, 10, seed=1)
    n_grow = int(1.2 * 100) - 100
    k = explored_count(n_grow, 0.5)
    n_split, n_box, n_guided = apportion(k, (1.0, 1.0, 1.0))
    assert counts["added"] == n_grow and counts["explored"] == k and counts["relocated"] == 0
    assert params["means"].shape[0] == 100 + n_grow
    assert int((state["stats"][SEED_FLAG] > 0).sum()) == n_box + n_guided  # split children are not seeds
    assert torch.isfinite(params["means"]).all() and torch.isfinite(params["scales"]).all()


def test_the_error_maps_are_asked_for_only_with_guided_seeds():
    assert MCMCExploreStrategy().requirements() == frozenset()  # splits only
    assert MCMCExploreStrategy(explore_box=1.0).requirements() == frozenset()
    assert MCMCExploreStrategy(explore_guided=0.5).requirements() == frozenset({VIEW_ERRORS})
    strategy = MCMCExploreStrategy(cap_max=1000, growth_rate=0.0, explore_split=0.0, explore_box=1.0, **WINDOW)
    params, optimizers = _set(50, 5)
    state = strategy.initialize_state()
    views = _views(50)
    views[0].error = None  # what the pipeline gives a strategy that does not ask for it
    strategy.step_post_backward(params, optimizers, state, 10, views, lr=1.6e-4,
                                generator=torch.Generator().manual_seed(0))
    assert "views" not in state and strategy.exploration_summary(state)["seeds_alive"] == 5


def test_explorers_that_stay_dead_are_relocated_again():
    strategy = MCMCExploreStrategy(cap_max=1000, growth_rate=0.0, explore_share=1.0, explore_split=0.0,
                                   explore_box=1.0, explore_guided=0.0, **WINDOW)
    params, optimizers = _set(100, 10)
    state = strategy.initialize_state()
    _step(strategy, params, optimizers, state, 10, seed=1)
    seeds = state["stats"][SEED_FLAG] > 0
    assert int(seeds.sum()) == 10
    with torch.no_grad():
        params["opacities"][seeds] = -8.0  # the seeds explained nothing and died
    counts = _step(strategy, params, optimizers, state, 20, seed=2)
    assert counts["relocated"] == 10 and counts["explored"] == 10
    assert float(torch.sigmoid(params["opacities"].detach()).min()) > 0.002


def test_bad_settings_are_refused():
    with pytest.raises(StrategyError, match="explore_share"):
        MCMCExploreStrategy(explore_share=1.5)
    with pytest.raises(StrategyError, match="explore_opacity"):
        MCMCExploreStrategy(explore_opacity=0.001)
    with pytest.raises(StrategyError, match="positive sum"):
        MCMCExploreStrategy(explore_split=0.0, explore_box=0.0, explore_guided=0.0)
    with pytest.raises(StrategyError, match="cap_max"):
        MCMCStrategy(cap_max="many")


# ------------------------------------------------------------------------------ the automatic cap
def _decisions(means, min_drop=MCMCStrategy.auto_min_drop, span=1, patience=MCMCStrategy.auto_patience):
    """Feed window means to the rule; the grow decision of each refinement until it stops."""
    below, out = 0, []
    for j in range(len(means)):
        grow, below = keeps_growing(list(means[:j + 1]), below, min_drop, span, patience)
        out.append(grow)
        if not grow:
            break
    return out


def test_auto_rule_grows_while_the_loss_falls_and_stops_when_it_is_flat():
    assert (MCMCStrategy.auto_min_drop, MCMCStrategy.auto_patience) == (0.05, 2)  # as docs/strategies.md states
    falling = [0.2 * 0.92 ** j for j in range(30)]  # 8% per refinement
    assert _decisions(falling) == [True] * 30
    flat = [0.1] * 10
    assert _decisions(flat) == [True, True, False]  # the first is judged on nothing; two flat in a row stop
    slowing = [0.2 * math.exp(-0.3 * (1 - math.exp(-j / 8)) * 8) for j in range(40)]  # the fall fades out
    decisions = _decisions(slowing)
    assert decisions[-1] is False and 3 < len(decisions) < 40
    rising = [0.1, 0.11, 0.12]
    assert _decisions(rising) == [True, True, False]


def test_auto_rule_on_a_noisy_loss_is_as_documented():
    g = torch.Generator().manual_seed(0)
    noise = (torch.rand(60, generator=g) * 2 - 1).tolist()
    # a flat loss with +-1% noise: every drop is below 5%, so it stops at the second window
    assert _decisions([0.1 * (1 + 0.01 * e) for e in noise]) == [True, True, False]
    # a fall of 8% per window with +-1% noise: every drop is above 5%, it keeps growing
    assert _decisions([0.1 * 0.92 ** j * (1 + 0.01 * e) for j, e in enumerate(noise)]) == [True] * 60
    # a loss whose drop crosses the threshold every other window never has two below in a row
    alternating = [0.1]
    for j in range(20):
        alternating.append(alternating[-1] * (0.93 if j % 2 == 0 else 0.99))
    assert all(_decisions(alternating))


def test_auto_rule_compares_slow_averages_over_span_windows():
    span = 4
    # nothing is judged before 2 x span windows; then a flat loss stops after patience windows
    assert _decisions([0.1] * 20, min_drop=0.02, span=span, patience=2) == [True] * (2 * span) + [False]
    # the drop is between the means of two neighbouring spans: a fall of 1% per window is about
    # 4% per span of 4, so it keeps growing at a 2% threshold, and stops at 5%
    falling = [0.1 * 0.99 ** j for j in range(40)]
    assert all(_decisions(falling, min_drop=0.02, span=span, patience=2))
    assert _decisions(falling, min_drop=0.05, span=span, patience=2) == [True] * (2 * span) + [False]
    # span 1 is the window-to-window rule: its threshold is per window, so the same fall stops it
    assert _decisions(falling, min_drop=0.02, span=1, patience=2) == [True, True, False]


def test_auto_rule_span_damps_the_noise_of_a_window():
    """A loss that falls 1.5% per window under +-5% window noise (the views a window drew): the
    window-to-window rule sees drops below 3% two windows in a row early and stops, while the
    slow average over 8 windows sees 11-12% per span and keeps growing for the whole run."""
    g = torch.Generator().manual_seed(1)
    noise = (torch.rand(80, generator=g) * 2 - 1).tolist()
    means = [0.1 * 0.985 ** j * (1 + 0.05 * e) for j, e in enumerate(noise)]
    assert len(_decisions(means, min_drop=0.03, span=1, patience=2)) < 10
    assert all(_decisions(means, min_drop=0.08, span=8, patience=2))  # 1% per window, as a span of 8


def test_auto_cap_freezes_the_count_when_the_loss_stops_falling():
    strategy = MCMCStrategy(cap_max="auto", **WINDOW)
    params, optimizers = _set(100, 0)
    state = strategy.initialize_state()
    sizes, loss = [], 0.2
    for step in range(3, 100):
        if step < 50:
            loss *= 0.98  # 18% per 10-step window: grow
        # flat from step 49 on: the window 51-60 still falls from 41-50; 61-70 and 71-80 are
        # flat, two in a row, so the refinement at 80 stops growth at the count of step 70
        _step(strategy, params, optimizers, state, step, seed=step, loss=torch.tensor(loss))
        sizes.append((step, params["means"].shape[0]))
    count = dict(sizes)
    assert count[10] > 100 and count[20] > count[10] and count[60] > count[50] and count[70] > count[60]
    assert count[80] == count[70] == count[99] == state["auto_cap"]
    assert strategy.exploration_summary(state) == {"auto_cap": count[70]}


def test_auto_state_of_a_checkpoint_from_before_auto_span_resumes_as_span_1():
    from exploregs_plugin.strategies.mcmc import auto_close_window, auto_state

    old = {"auto_loss": torch.tensor(0.5 * 10, dtype=torch.float64), "auto_steps": 10, "auto_previous": 0.5,
           "auto_below": 1, "auto_cap": None}  # a flat window after one below: the second stops growth
    assert auto_close_window(old, 1234, 0.05, 1, 2) == 1234 and old["auto_means"] == [0.5, 0.5]
    assert "auto_previous" not in old
    new = dict(auto_state(), auto_loss=torch.tensor(5.0, dtype=torch.float64), auto_steps=10, auto_means=[0.5],
               auto_below=1)
    assert auto_close_window(new, 1234, 0.05, 1, 2) == 1234


def test_auto_cap_needs_the_loss():
    strategy = MCMCStrategy(cap_max="auto", **WINDOW)
    params, optimizers = _set(20, 0)
    with pytest.raises(StrategyError, match="loss="):
        _step(strategy, params, optimizers, strategy.initialize_state(), 3, seed=0)


def test_cap_max_parses_as_auto_or_a_count():
    from exploregs_plugin.scripts.train import parse_config

    for method in ("exploregs-mcmc", "exploregs-mcmc-explore"):
        assert parse_config([method, "--strategy.cap-max", "auto"]).pipeline.strategy.cap_max == "auto"
        assert parse_config([method, "--strategy.cap-max", "5000"]).pipeline.strategy.cap_max == 5000
    strategy = parse_config(["exploregs-mcmc-explore", "--strategy.explore-share", "0.25"]).pipeline.strategy
    assert type(strategy) is MCMCExploreStrategy and strategy.explore_share == 0.25


def test_auto_state_survives_a_copy():
    """The automatic cap's state (the loss window as a tensor) is what a checkpoint saves."""
    strategy = MCMCStrategy(cap_max="auto", **WINDOW)
    params, optimizers = _set(50, 0)
    state = strategy.initialize_state()
    for step in (3, 4, 5):
        _step(strategy, params, optimizers, state, step, seed=step, loss=torch.tensor(0.1 + step))
    saved = copy.deepcopy(state)
    assert saved["auto_steps"] == 3 and float(saved["auto_loss"]) == pytest.approx(0.3 + 12)
