"""The significance prune (strategies/significance_prune.py) and the height-scaled threshold of Default."""

from __future__ import annotations

import pytest
import torch

from exploregs_plugin.io.config_files import config_from_dict, config_to_dict
from exploregs_plugin.model import GaussianModelConfig
from exploregs_plugin.engine.pipeline import strategy_for_renderer
from exploregs_plugin.rasterizer import RasterSettings
from exploregs_plugin.strategies import DefaultStrategy, OcclusionSplittingStrategy, SeedSplitStrategy, StrategyError
from exploregs_plugin.model.significance import visibility_cut_order
from exploregs_plugin.strategies.count_rule import evenly_spread, paired_deficit
from exploregs_plugin.strategies.default import CHECKED_SHARES, ndc_gradient_norms
from exploregs_plugin.strategies.requirements import VISIBILITY_STATS
from exploregs_plugin.strategies.significance_prune import (WEIGHT, WEIGHT_PEAK, WEIGHT_VIEWS, accumulate_weights,
                                                            least_significant, window_follows_reset)
from exploregs_plugin.strategies.synthetic import make_gaussians, make_optimizers, synthetic_views

W, H = 64, 48


def test_least_significant_takes_the_smallest_weights_up_to_the_share_and_never_an_undrawn_row():
    weights = torch.tensor([5.0, 1.0, 0.5, 3.0, 0.2, 0.0])
    views = torch.tensor([1.0, 2.0, 1.0, 1.0, 1.0, 0.0])  # the last row: no view drew it
    # total 9.7; ascending 0.2, 0.5, 1.0 add up to 1.7 <= 0.2 x 9.7 = 1.94; + 3.0 would not
    assert least_significant(weights, views, 0.2).tolist() == [False, True, True, False, True, False]
    assert not least_significant(weights, views, 0.0).any()
    assert least_significant(weights, views, 0.01).tolist() == [False, False, False, False, False, False]


def test_least_significant_keeps_at_least_the_unpruned_share_and_breaks_ties_by_index():
    g = torch.Generator().manual_seed(3)
    weights = torch.rand(500, generator=g) ** 4 * 100.0
    views = torch.ones(500)
    for share in (0.001, 0.05, 0.5, 0.9):
        pruned = least_significant(weights, views, share)
        assert weights[pruned].double().sum() <= share * weights.double().sum()
        # every kept row paints at least as much as every pruned one
        if pruned.any() and (~pruned).any():
            assert weights[~pruned].min() >= weights[pruned].max()
    ties = least_significant(torch.ones(4), torch.ones(4), 0.5)
    assert ties.tolist() == [True, True, False, False]


def test_least_significant_cuts_in_the_order_of_the_score_within_the_weights_share():
    weights = torch.tensor([5.0, 1.0, 0.5, 3.0, 0.2])
    views = torch.ones(5)
    score = torch.tensor([9.0, 0.1, 4.0, 0.05, 0.2])  # rows 3, 1, 4 first, then 2
    # total 9.7: 3.0 + 1.0 = 4.0 <= 0.45 x 9.7 = 4.365, + 0.2 = 4.2 also, + 0.5 = 4.7 not
    assert least_significant(weights, views, 0.45, score).tolist() == [False, True, False, True, True]
    # a non-finite score ranks as 0: cut first, still within the share
    assert least_significant(weights, views, 0.03, torch.tensor([1.0, 1.0, 1.0, 1.0, float("nan")])).tolist() == \
        [False, False, False, False, True]


def test_least_significant_prunes_nothing_where_the_drawn_rows_paint_nothing():
    assert not least_significant(torch.zeros(5), torch.ones(5), 0.5).any()
    assert not least_significant(torch.zeros(0), torch.zeros(0), 0.5).any()


def test_a_window_that_began_at_an_opacity_reset_is_not_judged():
    # resets at 200, 400, ...; refinements every 100, the reset after that step's prune
    assert not window_follows_reset(100, 100, 200)
    assert not window_follows_reset(200, 100, 200)  # its reset comes after its own prune
    assert window_follows_reset(300, 100, 200)  # views 201..300 all follow the reset at 200
    assert not window_follows_reset(400, 100, 200)
    assert window_follows_reset(750, 150, 200)  # 601..750 follow the reset at 600


def test_accumulated_weights_skip_non_finite_values_and_count_the_drawing_views():
    stats: dict[str, torch.Tensor] = {}
    nan, inf = float("nan"), float("inf")
    accumulate_weights(stats, torch.tensor([[1.0, 2.0, 0.5], [nan, 1.0, 0.25], [2.0, 3.0, 0.75]]),
                       torch.tensor([True, True, False]))
    accumulate_weights(stats, torch.tensor([[0.5, 1.0, 0.125], [4.0, 5.0, 0.5], [inf, 1.0, inf]]),
                       torch.tensor([True, True, True]))
    assert stats[WEIGHT].tolist() == [1.5, 4.0, 2.0]
    assert stats[WEIGHT_PEAK].tolist() == [0.5, 0.5, 0.75]  # the largest of the views', not their sum
    assert stats[WEIGHT_VIEWS].tolist() == [2.0, 2.0, 1.0]
    # a window saved before the peak was kept (no WEIGHT_PEAK) goes on from its sums
    old = {WEIGHT: torch.tensor([1.0, 2.0]), WEIGHT_VIEWS: torch.tensor([1.0, 1.0])}
    accumulate_weights(old, torch.tensor([[0.5, 1.0, 0.25], [0.0, 0.0, 0.0]]), torch.tensor([True, False]))
    assert old[WEIGHT].tolist() == [1.5, 2.0] and old[WEIGHT_PEAK].tolist() == [0.25, 0.0]


def _strategy(**kw) -> DefaultStrategy:
    base = dict(refine_start_iter=5, refine_stop_iter=100, refine_every=10, reset_every=1000,
                grow_grad2d=1e9, prune_opa=0.0, prune_weight_share=0.1)
    base.update(kw)
    return DefaultStrategy(**base)


def _run_window(strategy: DefaultStrategy, weights: torch.Tensor, last_step: int, first_step: int = 1):
    g = torch.Generator().manual_seed(0)
    n = weights.shape[0]
    params = make_gaussians(n, g)
    optimizers = make_optimizers(params)
    state = strategy.initialize_state()
    counts = {}
    for step in range(first_step, last_step + 1):
        views = synthetic_views(torch.zeros(n, 2), torch.ones(n, dtype=torch.bool), W, H, weights=weights)
        counts = strategy.step_post_backward(params, optimizers, state, step, views, generator=g)
    return params, state, counts


def test_a_refinement_prunes_the_rows_that_painted_least_of_the_window():
    weights = torch.tensor([10.0, 0.01, 5.0, 0.02, 8.0, 0.5])
    params, state, counts = _run_window(_strategy(), weights, 10)
    # total 23.53 a view; 0.01 + 0.02 + 0.5 = 0.53 <= 10% of it, + 5.0 would not be
    assert counts["pruned_significance"] == 3 and counts["pruned"] == 3
    assert params["means"].shape[0] == 3
    assert state["significance_pruned"] == 3
    assert float(state["stats"][WEIGHT].abs().sum()) == 0.0  # cleared for the next window


def test_the_prune_is_off_for_a_users_count_and_at_share_zero():
    weights = torch.tensor([10.0, 0.01, 5.0])
    for strategy in (_strategy(cap_max=100), _strategy(prune_weight_share=0.0)):
        params, _, counts = _run_window(strategy, weights, 10)
        assert params["means"].shape[0] == 3 and "pruned_significance" not in counts
        assert VISIBILITY_STATS not in strategy.requirements()
    assert VISIBILITY_STATS in _strategy().requirements()
    assert VISIBILITY_STATS not in DefaultStrategy().requirements()  # off by default
    assert VISIBILITY_STATS in SeedSplitStrategy(prune_weight_share=0.05).requirements()


def test_the_end_of_growth_judges_once_more_and_says_the_count():
    weights = torch.tensor([10.0, 0.01, 5.0, 0.02])
    strategy = _strategy(refine_stop_iter=15)
    params, state, counts = _run_window(strategy, weights, 15, first_step=11)
    assert counts["pruned_significance"] == 2 and params["means"].shape[0] == 2
    note = strategy.count_decision(state)
    assert note.startswith("count: 2 Gaussians at the end of growth (step 15)") and "10.0%" in note


def test_a_renderer_without_the_sums_runs_the_strategy_without_the_prune():
    gsplat = GaussianModelConfig(raster=RasterSettings(backend="gsplat"))
    chosen, notes = strategy_for_renderer(DefaultStrategy(prune_weight_share=0.05), gsplat, torch.device("cuda"))
    assert chosen.prune_weight_share == 0.0 and len(notes) == 1 and "gsplat" in notes[0]
    occlusion = OcclusionSplittingStrategy(prune_weight_share=0.05)
    assert strategy_for_renderer(occlusion, gsplat, torch.device("cuda")) == (occlusion, [])  # needs the sums anyway
    kept, none = strategy_for_renderer(DefaultStrategy(prune_weight_share=0.05), GaussianModelConfig(),
                                       torch.device("cpu"))
    assert kept.prune_weight_share == 0.05 and none == []


def test_the_end_of_run_cut_removes_the_least_significant_rows_and_says_the_count():
    g = torch.Generator().manual_seed(0)
    params = make_gaussians(6, g)
    optimizers = make_optimizers(params)
    strategy = DefaultStrategy(final_weight_share=0.1)
    state = strategy.initialize_state()
    kept_means = params["means"].detach()[[0, 2, 4]].clone()
    weights = torch.tensor([10.0, 0.5, 5.0, 0.01, 4.0, 0.0], dtype=torch.float64)  # total 19.51: 0.51 <= 10%
    # row 5: drawn by no training view, so it paints nothing training sees: cut at no cost to the share
    drawn = torch.tensor([3.0, 1.0, 2.0, 1.0, 2.0, 0.0], dtype=torch.float64)
    peaks = torch.tensor([0.5, 0.5, 0.5, 0.5, 0.5, 0.0], dtype=torch.float64)
    visibility = torch.stack([weights, drawn, peaks, weights], dim=1)  # one view's: its weight is the view weight
    assert strategy.final_cut(params, optimizers, state, visibility, step=99) == 3
    assert torch.equal(params["means"].detach(), kept_means)
    assert optimizers["means"].param_groups[0]["params"][0] is params["means"]  # the optimizer follows
    assert strategy.count_decision(state).startswith("count: 3 of 6 Gaussians kept after the last step (100)")
    for off in (DefaultStrategy(final_weight_share=0.0), DefaultStrategy(cap_max=100)):  # off, or the user's count
        assert off.final_cut_share() == 0.0
        assert off.final_cut(params, optimizers, off.initialize_state(), visibility[:3], 99) == 0
    assert DefaultStrategy().final_cut_share() == 0.003 == SeedSplitStrategy().final_cut_share()


def test_the_end_of_run_cut_spends_its_share_on_faint_rows_and_keeps_a_row_that_paints_pixels_alone():
    params = make_gaussians(6, torch.Generator().manual_seed(1))
    optimizers = make_optimizers(params)
    strategy = DefaultStrategy(final_weight_share=0.1)
    weights = torch.tensor([10.0, 0.6, 5.0, 1.2, 4.0, 0.7], dtype=torch.float64)  # total 21.5: budget 2.15
    peaks = torch.tensor([0.5, 0.9, 0.5, 0.02, 0.5, 0.03], dtype=torch.float64)
    visibility = torch.stack([weights, torch.ones(6, dtype=torch.float64), peaks, weights], dim=1)
    kept_means = params["means"].detach()[[0, 1, 2, 4]].clone()
    # by weight alone rows 1 and 5 (0.6 + 0.7) would go; by weight x peak rows 5 and 3 (0.7 + 1.2),
    # and row 1, which paints its pixels almost alone, stays
    assert least_significant(weights, torch.ones(6), 0.1).tolist() == [False, True, False, False, False, True]
    assert strategy.final_cut(params, optimizers, strategy.initialize_state(), visibility, step=9) == 2
    assert torch.equal(params["means"].detach(), kept_means)


def _checked_cut_case(tolerance: float, nan_at: int | None = None, loss_per_share: float = 10.0,
                      last: bool = True, settled_tolerance: float | None = 0.3):
    """A 300-row set whose weights span four decades (the last 5 rows drawn by no view), cut by
    Default's end-of-run rule with a check that scores 6 views: each view loses ``loss_per_share``
    dB per unit of blend-weight share removed, times (1 + v / 10) on view v, and every view scores
    NaN from the ``nan_at``-th call on. Returns (rows kept, note, the masks the check saw, the
    visibility)."""
    g = torch.Generator().manual_seed(5)
    n = 300
    params = make_gaussians(n, g)
    optimizers = make_optimizers(params)
    weights = 10.0 ** (4.0 * torch.rand(n, generator=g, dtype=torch.float64))
    drawn = torch.ones(n, dtype=torch.float64)
    weights[-5:], drawn[-5:] = 0.0, 0.0
    visibility = torch.stack([weights, drawn, torch.ones(n, dtype=torch.float64), weights], 1)
    seen: list[torch.Tensor] = []

    def score_without(rows: torch.Tensor) -> list[float]:
        seen.append(rows.clone())
        if nan_at is not None and len(seen) > nan_at:
            return [float("nan")] * 6
        removed = float(weights[rows].sum() / weights.sum())
        return [30.0 - loss_per_share * removed * (1.0 + v / 10.0) for v in range(6)]

    strategy = DefaultStrategy(final_cut_tolerance=tolerance, settled_cut_tolerance=settled_tolerance)
    state = strategy.initialize_state()
    strategy.final_cut(params, optimizers, state, visibility, step=99, score_without=score_without, last=last)
    return params["means"].shape[0], strategy.count_decision(state), seen, visibility


def _ladder(visibility: torch.Tensor) -> tuple[list[float], list[torch.Tensor]]:
    weights, order = visibility[:, 0], visibility_cut_order(visibility)
    shares = [0.003, *CHECKED_SHARES]
    return shares, [least_significant(weights, torch.ones_like(weights), q, order) for q in shares]


def test_the_end_of_run_cut_goes_on_while_the_checked_views_lose_at_most_the_tolerance():
    kept, note, seen, visibility = _checked_cut_case(tolerance=0.1)
    weights = visibility[:, 0]
    shares, ladder = _ladder(visibility)
    # the whole set scored, then the default share and each larger one until one costs more
    assert not seen[0].any() and all(torch.equal(a, b) for a, b in zip(seen[1:], ladder))
    deficits = [paired_deficit([30.0] * 6, [30.0 - 10.0 * float(weights[m].sum() / weights.sum()) * (1 + v / 10)
                                           for v in range(6)]) for m in ladder]
    passed = [d <= 0.1 for d in deficits]
    last = passed.index(False) - 1  # the cuts are nested: the deficit grows with the share
    assert last >= 1 and not any(passed[last + 1:]) and len(seen) == last + 3
    assert kept == int((~ladder[last]).sum())
    assert (f"at most {shares[last]:.1%} of the training views' blend weight" in note
            and f"the 6 training views checked lose {deficits[last]:.2f} dB" in note
            and f"{shares[last + 1]:.1%} would lose {deficits[last + 1]:.2f} dB" in note)


def test_a_cut_the_views_refuse_at_the_first_share_leaves_only_the_rows_no_view_draws():
    kept, note, seen, visibility = _checked_cut_case(tolerance=0.1, loss_per_share=100.0)
    assert len(seen) == 2 and kept == 295  # the 5 undrawn rows, which paint nothing, go for free
    assert "the 5 that no training view draws were cut; the 6 training views checked lose nothing" in note
    assert "0.3% would lose" in note


def test_the_checked_cut_is_off_at_tolerance_0_and_refuses_a_share_whose_views_score_nan():
    kept_off, note_off, seen_off, visibility = _checked_cut_case(tolerance=0.0)
    _, ladder = _ladder(visibility)
    assert seen_off == [] and kept_off == int((~ladder[0]).sum()) and "checked" not in note_off
    # a candidate whose renders are not finite is never kept: the cut stays at the last finite one
    kept, note, seen, _ = _checked_cut_case(tolerance=10.0, nan_at=2)
    assert len(seen) == 3 and kept == int((~ladder[0]).sum()) and "0.5% would lose nan dB" in note
    # a generous tolerance takes every share tried, and the line says where the search stopped
    kept_all, note_all, seen_all, _ = _checked_cut_case(tolerance=1e6)
    assert len(seen_all) == 2 + len(CHECKED_SHARES) and kept_all == int((~ladder[-1]).sum())
    assert note_all.endswith("--strategy.final-cut-tolerance); the largest share tried "
                             "(--strategy.final-weight-share 0 keeps them)")


def test_the_settled_cut_is_checked_with_its_own_tolerance():
    """The settled cut (training follows it) takes each share its views lose at most
    settled_cut_tolerance on; the cut after the last step keeps final_cut_tolerance; None: the
    settled cut checked as the last."""
    _, ladder = _ladder(_checked_cut_case(tolerance=0.1)[3])
    strict = _checked_cut_case(tolerance=0.1, last=True, settled_tolerance=1e6)
    loose = _checked_cut_case(tolerance=0.1, last=False, settled_tolerance=1e6)
    same = _checked_cut_case(tolerance=0.1, last=False, settled_tolerance=None)
    assert strict[0] > loose[0] == int((~ladder[-1]).sum())  # every share passes at 1e6 dB
    assert same[0] == strict[0] and same[2] and all(torch.equal(a, b) for a, b in zip(same[2], strict[2]))
    assert "(at most 1e+06, --strategy.settled-cut-tolerance)" in loose[1]
    assert "for the rest of the run" in loose[1] and "(at most 0.1, --strategy.final-cut-tolerance)" in same[1]


def test_the_checks_renders_are_the_run_without_those_rows(tmp_path):
    """Pipeline.view_psnrs without rows gives, bit for bit, the PSNRs of the set with those rows
    removed (row_ops.remove), and without none those of the whole set."""
    from dataclasses import replace

    from exploregs_plugin.method_configs import get_method
    from exploregs_plugin.strategies import row_ops

    config = get_method("exploregs-seedsplit").config
    config = replace(config, data="builtin:tiny", max_steps=12, run_dir=tmp_path / "run", eval_count=1,
                     tensorboard=False, save_eval_images=False, quiet=True, num_threads=1)
    trainer = config.setup()
    trainer.train()
    pipeline = trainer.pipeline
    views = evenly_spread(len(pipeline.datamanager.train_cameras), 3)
    n = pipeline.model.num_gaussians
    rows = torch.zeros(n, dtype=torch.bool)
    rows[::3] = True
    whole = pipeline.view_psnrs(views, 11)
    assert pipeline.view_psnrs(views, 11, without=torch.zeros(n, dtype=torch.bool)) == whole
    without = pipeline.view_psnrs(views, 11, without=rows)
    assert all(w > o for w, o in zip(whole, without))  # a third of the set missing costs every view
    row_ops.remove(pipeline.params, pipeline.optimizers, {}, rows)
    assert pipeline.view_psnrs(views, 11) == without


def test_a_run_cuts_after_its_last_step_and_evaluates_the_cut_set(tmp_path):
    from dataclasses import replace

    from exploregs_plugin.method_configs import get_method

    def run(share: float, name: str):
        config = get_method("exploregs-seedsplit").config
        strategy = replace(config.pipeline.strategy, final_weight_share=share, settled_cut_iter=0)  # the last cut alone
        config = replace(config, data="builtin:tiny", max_steps=12, run_dir=tmp_path / name, eval_count=1,
                         tensorboard=False, save_eval_images=False, quiet=True, num_threads=1,
                         pipeline=replace(config.pipeline, strategy=strategy))
        trainer = config.setup()
        return trainer.train(), trainer.pipeline.model.num_gaussians

    cut, n_cut = run(0.05, "cut")
    whole, n_whole = run(0.0, "whole")
    assert n_cut == cut["num_gaussians"] < n_whole == whole["num_gaussians"]
    assert cut["count_decision"].startswith(f"count: {n_cut:,} of {n_whole:,} Gaussians kept after the last step (12)")
    assert not whole.get("count_decision") and "cut_lines" not in whole
    assert cut["cut_lines"] == [cut["count_decision"]]  # the one cut's line


def test_fields_are_checked():
    with pytest.raises(StrategyError, match="final_weight_share"):
        DefaultStrategy(final_weight_share=1.0)
    with pytest.raises(StrategyError, match="final_cut_tolerance"):
        DefaultStrategy(final_cut_tolerance=float("nan"))
    with pytest.raises(StrategyError, match="prune_weight_share"):
        DefaultStrategy(prune_weight_share=1.0)
    with pytest.raises(StrategyError, match="grow_grad2d_height"):
        DefaultStrategy(grow_grad2d_height=0)
    with pytest.raises(StrategyError, match="settled_cut_iter"):
        DefaultStrategy(settled_cut_iter=-1)
    for frac in (0.0, 1.0, float("nan")):
        with pytest.raises(StrategyError, match="settled_cut_frac"):
            DefaultStrategy(settled_cut_frac=frac)
    with pytest.raises(StrategyError, match="settled_cut_tolerance"):
        DefaultStrategy(settled_cut_tolerance=-0.1)


def test_a_config_saved_before_the_fields_existed_loads_as_it_trained():
    saved = config_to_dict(SeedSplitStrategy(grow_grad2d_height=720, prune_weight_share=0.01, final_weight_share=0.01,
                                             final_cut_tolerance=0.5, settled_cut_iter=900, settled_cut_frac=0.5,
                                             settled_cut_tolerance=1.0))
    del saved["grow_grad2d_height"], saved["prune_weight_share"], saved["final_weight_share"]
    del saved["final_cut_tolerance"], saved["settled_cut_iter"], saved["settled_cut_frac"], saved["settled_cut_tolerance"]
    loaded = config_from_dict(saved)
    assert loaded.grow_grad2d_height is None and loaded.prune_weight_share == 0.0 and loaded.final_weight_share == 0.0
    assert loaded.final_cut_tolerance == 0.0 and SeedSplitStrategy().final_cut_tolerance == 0.1
    assert loaded.settled_cut_iter == 0 and SeedSplitStrategy().settled_cut_iter is None
    # saved between the settled cut and its own fraction and tolerance: two thirds, checked as the last
    saved = config_to_dict(SeedSplitStrategy())
    del saved["settled_cut_frac"], saved["settled_cut_tolerance"]
    loaded = config_from_dict(saved)
    assert loaded.settled_cut_iter is None and loaded.settled_cut_frac == 2.0 / 3.0
    assert loaded.settled_cut_tolerance is None and loaded._cut_tolerance(last=False) == (
        0.1, "--strategy.final-cut-tolerance")
    from exploregs_plugin.schedule import ScheduleConfig

    assert loaded.setup(ScheduleConfig().resolve(1500)).settled_cut_step(1500) == 1000


def test_the_settled_cut_comes_at_four_fifths_of_the_run_after_growth_and_before_the_last_step():
    from exploregs_plugin.schedule import ScheduleConfig

    schedule = ScheduleConfig().resolve(1500)
    strategy = DefaultStrategy().setup(schedule)
    assert strategy.refine_stop_iter == 750 and strategy.settled_cut_iter == 1200
    assert strategy.settled_cut_step(1500) == 1200
    assert DefaultStrategy(settled_cut_frac=2.0 / 3.0).setup(schedule).settled_cut_step(1500) == 1000
    assert DefaultStrategy(settled_cut_iter=1200).setup(schedule).settled_cut_step(1500) == 1200  # the user's step
    for off in (DefaultStrategy(settled_cut_iter=0),  # the last cut alone
                DefaultStrategy(settled_cut_iter=750), DefaultStrategy(settled_cut_iter=600),  # growth not over
                DefaultStrategy(settled_cut_iter=1499), DefaultStrategy(settled_cut_iter=1500),  # the last cut's place
                DefaultStrategy(final_weight_share=0.0), DefaultStrategy(cap_max=5000)):  # no cut at all
        assert off.setup(schedule).settled_cut_step(1500) is None, off
    assert DefaultStrategy(refine_stop_iter=750).settled_cut_step(1500) is None  # no schedule: not filled, no cut


def test_the_height_scaled_statistic_is_the_one_at_the_reference_height():
    grads = torch.tensor([[[3e-5, 4e-5], [1e-5, 0.0]]])
    plain = ndc_gradient_norms(grads, W, H)
    assert torch.equal(ndc_gradient_norms(grads, W, H, reference_height=H), plain)
    assert torch.allclose(ndc_gradient_norms(grads, W, H, reference_height=4 * H), plain / 4, rtol=1e-6)
    # a coarse level of a view whose full size is 2H: the statistic of the full-size view
    level = ndc_gradient_norms(grads, W // 2, H // 2, downscale=2, reference_height=H)
    assert torch.allclose(level, ndc_gradient_norms(grads, W // 2, H // 2, downscale=2) * 1.0, rtol=1e-6)
