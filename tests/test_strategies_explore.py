"""Random Seeding, Random Splitting, Seed+Split, budgets and hard cases (strategy level)."""

from __future__ import annotations

import math
from dataclasses import fields

import pytest
import torch

from exploregs_plugin.schedule import ScheduleConfig
from exploregs_plugin.strategies import (
    BUDGET_PRESETS,
    DefaultStrategy,
    ExplorationStrategy,
    SeedingStrategy,
    SeedSplitStrategy,
    SplittingStrategy,
    StrategyError,
    resolve_budget,
    scaled_budget,
)
from exploregs_plugin.strategies.budget import SEED_FRACTION, SPLIT_FRACTION
from exploregs_plugin.rasterizer.sh import SH_C0
from exploregs_plugin.strategies.seeding import SEED_FLAG, RandomSeeding, seed_rows
from exploregs_plugin.strategies.splitting import RandomSplitting, sample_split_indices
from exploregs_plugin.strategies.synthetic import make_gaussians, make_optimizers, synthetic_views

W, H = 32, 32
WINDOW = dict(refine_start_iter=2, refine_stop_iter=500, refine_every=10, reset_every=100)


def _info(params, grad=0.0, visible=True):
    n = params["means"].shape[0]
    return synthetic_views(torch.full((n, 2), grad), torch.full((n,), visible, dtype=torch.bool), W, H)


def _run(strategy, params, optimizers, state, steps, gen, grad=0.0, visible=True):
    history = []
    for step in steps:
        history.append(strategy.step_post_backward(params, optimizers, state, step, _info(params, grad, visible), generator=gen))
    return history


# ------------------------------------------------------------------------------ seeding
def test_seeding_counts_box_and_disable():
    g = torch.Generator().manual_seed(0)
    params = make_gaussians(50, g)
    optimizers = make_optimizers(params)
    lo = params["means"].detach().min(0).values
    hi = params["means"].detach().max(0).values
    s = SeedingStrategy(seeding=RandomSeeding(n_seed=7, every=10), grow_grad2d=1e9, prune_opa=0.0, **WINDOW)
    state = s.initialize_state()
    gen = torch.Generator().manual_seed(1)
    history = _run(s, params, optimizers, state, range(1, 41), gen)
    seeded = [c["seeded"] for c in history]
    assert seeded == [7 if step in (10, 20, 30, 40) else 0 for step in range(1, 41)]
    assert params["means"].shape[0] == 50 + 28
    # Seeds of the first round lie in the box of the original centres.
    first = params["means"].detach()[50:57]
    assert torch.all(first >= lo - 1e-6) and torch.all(first <= hi + 1e-6)
    assert s.exploration_summary(state)["seeds_alive"] == 28
    assert int(state["stats"][SEED_FLAG].sum()) == 28

    off = SeedingStrategy(seeding=RandomSeeding(n_seed=0, every=10), **WINDOW)
    p2 = make_gaussians(50, torch.Generator().manual_seed(0))
    history = _run(off, p2, make_optimizers(p2), off.initialize_state(), range(1, 41), gen)
    assert all(c["seeded"] == 0 for c in history)
    assert p2["means"].shape[0] == 50


def test_seed_attributes_follow_the_formulas():
    g = torch.Generator().manual_seed(3)
    params = make_gaussians(30, g, sh_degree=2, extent=2.0)
    center = torch.tensor([0.1, -0.2, 0.3])
    rows = seed_rows(params["means"], params["scales"], 500, torch.Generator().manual_seed(4), center, 8)
    means = params["means"].detach()
    r_old = (means - center).norm(dim=-1)
    ratio = (torch.exp(params["scales"].detach()).mean(-1) / r_old).mean()
    r_new = (rows["means"] - center).norm(dim=-1)
    # Isotropic scale s_new = r_new * mean_i(mean_axis(s_i) / r_i).
    s_new = torch.exp(rows["scales"])
    assert torch.allclose(s_new, (r_new * ratio)[:, None].expand(500, 3), rtol=1e-5)
    # Opacity 0.2 + 0.5 r / max r, so it spans [0.2, 0.7] and is 0.7 for the farthest seed.
    o = torch.sigmoid(rows["opacities"])
    assert torch.allclose(o, 0.2 + 0.5 * r_new / r_new.max(), atol=1e-6)
    assert abs(float(o.max()) - 0.7) < 1e-6
    # Colour uniform in [0, 1]^3 (mean ~ 0.5), higher SH zero, unit quaternions.
    rgb = rows["sh0"][:, 0] * SH_C0 + 0.5
    assert rgb.min() >= 0 and rgb.max() <= 1 and abs(float(rgb.mean()) - 0.5) < 0.05
    assert rows["shN"].shape == (500, 8, 3) and torch.count_nonzero(rows["shN"]) == 0
    assert torch.allclose(rows["quats"].norm(dim=-1), torch.ones(500), atol=1e-6)
    # Positions uniform in the box: each axis covers it, mean near the centre of the box.
    lo, hi = means.min(0).values, means.max(0).values
    assert torch.all(rows["means"] >= lo) and torch.all(rows["means"] <= hi)
    assert torch.allclose(rows["means"].mean(0), (lo + hi) / 2, atol=0.15 * float((hi - lo).max()))


def test_robust_box_trims_outliers():
    g = torch.Generator().manual_seed(5)
    params = make_gaussians(200, g)
    with torch.no_grad():
        params["means"][0] = torch.tensor([50.0, 50.0, 50.0])
    rows = seed_rows(params["means"], params["scales"], 100, torch.Generator().manual_seed(0), torch.zeros(3), 3, box="robust", box_quantile=0.01)
    assert rows["means"].abs().max() <= 1.0 + 1e-6
    rows = seed_rows(params["means"], params["scales"], 100, torch.Generator().manual_seed(0), torch.zeros(3), 3)
    assert rows["means"].max() > 2.0  # the paper's AABB keeps the far Gaussian's extent


def test_cameras_box_is_the_extent_cube_around_the_cameras_centre_whatever_the_centres():
    g = torch.Generator().manual_seed(5)
    params = make_gaussians(200, g)
    with torch.no_grad():
        params["means"][0] = torch.tensor([50.0, 50.0, 50.0])  # far outside: ignored by this box
    center = torch.tensor([1.0, -2.0, 0.5])
    rows = seed_rows(params["means"], params["scales"], 2000, torch.Generator().manual_seed(0), center, 3,
                     box="cameras", extent=3.0)
    offset = rows["means"] - center
    assert offset.abs().max() <= 3.0 + 1e-5 and offset.abs().max() > 2.9  # fills the cube, not more
    assert torch.allclose(offset.mean(0), torch.zeros(3), atol=0.2)
    assert seed_rows(params["means"][:0], params["scales"][:0], 5, g, center, 3, box="cameras") is None


def test_seeding_relaxes_size_prune_while_active():
    s = SeedingStrategy(seeding=RandomSeeding(n_seed=5, every=10), **WINDOW)
    assert s.size_prune_factor(200) == 10.0 and DefaultStrategy(**WINDOW).size_prune_factor(200) == 0.1
    assert SeedingStrategy(seeding=RandomSeeding(n_seed=0, every=10), **WINDOW).size_prune_factor(200) == 0.1


def test_seeding_hard_cases():
    gen = torch.Generator().manual_seed(0)
    s = SeedingStrategy(seeding=RandomSeeding(n_seed=4, every=10), **WINDOW)
    # N = 0: no box, no seeds, no crash.
    empty = make_gaussians(0, gen)
    state = s.initialize_state()
    assert _run(s, empty, make_optimizers(empty), state, [10], gen)[0]["seeded"] == 0
    # Zero-volume box: one Gaussian at the scene centre -> all seeds at that point, finite
    # attributes (scale floored, opacity 0.2).
    one = make_gaussians(1, gen)
    with torch.no_grad():
        one["means"].zero_()
    state = s.initialize_state(scene_scale=2.0)
    counts = _run(s, one, make_optimizers(one), state, [10], gen, grad=0.0)[0]
    assert counts["seeded"] == 4
    for key, p in one.items():
        assert torch.isfinite(p).all(), key
    assert torch.allclose(torch.sigmoid(one["opacities"][1:]), torch.full((4,), 0.2))
    # Non-finite centres are ignored by the box.
    rows = seed_rows(torch.tensor([[0.0, 0, 0], [1.0, 1, 1], [float("nan"), 0, 0]]), torch.zeros(3, 3), 10, gen, torch.zeros(3), 0)
    assert torch.isfinite(rows["means"]).all() and rows["means"].max() <= 1.0


def test_seeds_respect_cap_max():
    gen = torch.Generator().manual_seed(0)
    params = make_gaussians(20, gen)
    s = SeedingStrategy(seeding=RandomSeeding(n_seed=10, every=10), cap_max=25, grow_grad2d=1e9, prune_opa=0.0, **WINDOW)
    history = _run(s, params, make_optimizers(params), s.initialize_state(), [10, 20], gen)
    assert [c["seeded"] for c in history] == [5, 0]
    assert params["means"].shape[0] == 25


def _seeding_setup(n: int, n_seed: int, prune_opa: float):
    """(generator, params, optimizers, strategy, state): n random Gaussians, a seeding strategy
    every 10 steps with ADC growth off."""
    gen = torch.Generator().manual_seed(0)
    params = make_gaussians(n, gen)
    s = SeedingStrategy(seeding=RandomSeeding(n_seed=n_seed, every=10), grow_grad2d=1e9, prune_opa=prune_opa, **WINDOW)
    return gen, params, make_optimizers(params), s, s.initialize_state()


def test_seeds_outside_every_view_are_counted():
    gen, params, optimizers, s, state = _seeding_setup(10, n_seed=3, prune_opa=0.0)
    assert s.exploration_summary(state) == {"seeds_alive": 0, "seeds_unseen": 0}
    assert _run(s, params, optimizers, state, [10], gen)[0]["seeded"] == 3
    assert s.exploration_summary(state) == {"seeds_alive": 3, "seeds_unseen": 3}
    # The next view sees only the first seed.
    vis = torch.zeros(13, dtype=torch.bool)
    vis[10] = True
    s.step_post_backward(params, optimizers, state, 11, synthetic_views(torch.zeros(13, 2), vis, W, H), generator=gen)
    assert s.exploration_summary(state) == {"seeds_alive": 3, "seeds_unseen": 2}


def test_seed_probation_schedule():
    s = SeedingStrategy(seeding=RandomSeeding(n_seed=3, every=10), refine_start_iter=2, refine_stop_iter=10_000, refine_every=100,
                        reset_every=200)
    # Default grace: half the reset interval. The prune at a reset step comes before that reset.
    assert [s.seeding.judged_at(s, t) for t in (100, 200, 300, 400, 500)] == [True] * 5
    s.reset_every = 3000
    assert [s.seeding.judged_at(s, t) for t in (2900, 3000, 3100, 4400, 4500, 6000, 6100)] == [
        True, True, False, False, True, True, False]
    s.seeding.grace = 0
    assert s.seeding.judged_at(s, 3100)
    for bad in (dict(prune_opa=-0.1), dict(prune_opa=1.0), dict(grace=-1)):
        with pytest.raises(StrategyError):
            RandomSeeding(n_seed=3, every=10, **bad)


def test_seed_probation_prunes_faded_seeds_only():
    gen, params, optimizers, s, state = _seeding_setup(10, n_seed=4, prune_opa=0.005)
    assert _run(s, params, optimizers, state, [10], gen)[0]["seeded"] == 4
    # Two seeds and two original Gaussians fade to 0.02: under the seeds' prune_opa (0.05), over Default's.
    with torch.no_grad():
        params["opacities"][:] = torch.logit(torch.tensor(0.5))
        params["opacities"][[0, 1, 10, 11]] = torch.logit(torch.tensor(0.02))
    kept = params["means"].detach()[[0, 1, 12, 13]].clone()
    counts = _run(s, params, optimizers, state, [20], gen)[0]
    assert counts["seeds_pruned"] == 2 and counts["pruned"] == 2
    assert torch.equal(params["means"].detach()[[0, 1, 10, 11]], kept)  # faded originals stay
    assert s.exploration_summary(state)["seeds_alive"] == 2 + 4  # the two left and the next batch

    # Within the grace period after a reset nothing is judged; with the seeds' prune_opa = 0 never.
    with torch.no_grad():
        params["opacities"][10:] = torch.logit(torch.tensor(0.02))
    assert _run(s, params, optimizers, state, [110], gen)[0]["seeds_pruned"] == 0
    off = SeedingStrategy(seeding=RandomSeeding(n_seed=4, every=10, prune_opa=0.0), grow_grad2d=1e9, **WINDOW)
    p2 = make_gaussians(10, gen)
    st2 = off.initialize_state()
    _run(off, p2, make_optimizers(p2), st2, [10], gen)
    with torch.no_grad():
        p2["opacities"][10:] = torch.logit(torch.tensor(0.02))
    assert _run(off, p2, make_optimizers(p2), st2, [20], gen)[0]["seeds_pruned"] == 0
    assert p2["means"].shape[0] == 14 + 4


# ------------------------------------------------------------------------------ splitting
def test_random_split_splits_zero_gradient_gaussians():
    gen = torch.Generator().manual_seed(0)
    params = make_gaussians(30, gen)
    optimizers = make_optimizers(params)
    s = SplittingStrategy(splitting=RandomSplitting(n_split=4, every=1), prune_opa=0.0, **WINDOW)
    state = s.initialize_state()
    history = _run(s, params, optimizers, state, range(3, 8), gen, grad=0.0)
    assert [c["random_split"] for c in history] == [4] * 5
    assert all(c["cloned"] == 0 and c["split"] == 0 for c in history)  # ADC saw no gradient
    assert params["means"].shape[0] == 30 + 5 * 4
    # Outside the window nothing is split.
    assert _run(s, params, optimizers, state, [1, 2, 500, 600], gen)[0]["random_split"] == 0


def test_split_selection_frequency_follows_scale_chi_square():
    k = 8
    log_scales = torch.log(torch.linspace(0.01, 0.08, k))[:, None].repeat(1, 3)
    log_scales[:, 1] += 0.3  # anisotropic: the weight is the mean over axes
    weights = torch.exp(log_scales).mean(-1)
    p = weights / weights.sum()
    gen = torch.Generator().manual_seed(123)
    draws = 4000
    picks = torch.stack([sample_split_indices(log_scales, 1, gen) for _ in range(draws)]).flatten()
    observed = torch.bincount(picks, minlength=k).double()
    expected = p.double() * draws
    chi2 = float(((observed - expected) ** 2 / expected).sum())
    # Critical value of chi-square with k - 1 = 7 degrees of freedom at p = 0.001.
    assert chi2 < 24.32, chi2
    # A uniform choice would be rejected by the same test (the weighting matters).
    uniform = torch.full((k,), draws / k, dtype=torch.float64)
    assert float(((uniform - expected) ** 2 / expected).sum()) > 24.32


def test_split_multi_draw_picks_are_distinct_and_capped():
    gen = torch.Generator().manual_seed(0)
    log_scales = torch.randn(10, 3)
    for _ in range(50):
        idx = sample_split_indices(log_scales, 6, gen)
        assert len(idx) == 6 and len(set(idx.tolist())) == 6
    assert len(sample_split_indices(log_scales, 25, gen)) == 10  # n_split > N
    bad = log_scales.clone()
    bad[:4] = float("nan")
    assert set(sample_split_indices(bad, 10, gen).tolist()) == set(range(4, 10))
    assert len(sample_split_indices(torch.zeros(0, 3), 3, gen)) == 0


def test_random_split_children_drawn_from_parent():
    gen = torch.Generator().manual_seed(2)
    params = make_gaussians(1, gen)
    with torch.no_grad():
        params["scales"].copy_(torch.log(torch.tensor([[0.3, 0.1, 0.02]])))
        params["quats"].copy_(torch.tensor([[0.9, 0.1, -0.3, 0.2]]))
        params["means"].copy_(torch.tensor([[1.0, 2.0, 3.0]]))
    parent_mean = params["means"].detach().clone()
    parent = {k: v.detach().clone() for k, v in params.items()}
    from exploregs_plugin.rasterizer.projection import covariances_3d

    cov = covariances_3d(parent["quats"], torch.exp(parent["scales"]))[0].double()
    s = SplittingStrategy(splitting=RandomSplitting(n_split=1, every=1), prune_opa=0.0, grow_grad2d=1e9, **WINDOW)
    offsets = []
    for step in range(400):  # re-split a fresh copy of the same parent many times
        p = torch.nn.ParameterDict({k: torch.nn.Parameter(v.clone()) for k, v in parent.items()})
        s.splitting.random_split(s, p, make_optimizers(p), {"stats": {}}, gen)
        assert p["means"].shape[0] == 2
        assert torch.allclose(torch.exp(p["scales"].detach()), torch.exp(parent["scales"]).expand(2, 3) / 1.6, rtol=1e-5)
        offsets.append(p["means"].detach() - parent_mean)
    offsets = torch.cat(offsets).double()  # [800, 3] samples of N(0, Sigma_parent)
    sample_cov = offsets.T @ offsets / offsets.shape[0]
    assert torch.allclose(sample_cov, cov, atol=0.15 * float(cov.diagonal().max()))
    # Mahalanobis radii behave like a 3D standard normal: E|z|^2 = 3.
    z2 = torch.einsum("ni,ij,nj->n", offsets, torch.linalg.inv(cov), offsets)
    assert 2.6 < float(z2.mean()) < 3.4


def test_random_split_respects_cap_and_nonfinite():
    gen = torch.Generator().manual_seed(0)
    params = make_gaussians(10, gen)
    s = SplittingStrategy(splitting=RandomSplitting(n_split=20, every=1), cap_max=13, prune_opa=0.0, **WINDOW)
    counts = _run(s, params, make_optimizers(params), s.initialize_state(), [3, 4], gen)
    assert [c["random_split"] for c in counts] == [3, 0]
    assert params["means"].shape[0] == 13
    # Non-finite gradients do not stop random splitting (its choice ignores gradients).
    p2 = make_gaussians(6, gen)
    s2 = SplittingStrategy(splitting=RandomSplitting(n_split=20, every=1), prune_opa=0.0, **WINDOW)
    c = _run(s2, p2, make_optimizers(p2), s2.initialize_state(), [3], gen, grad=float("nan"))[0]
    assert c["random_split"] == 6 and c["nonfinite_grads"] == 6
    assert p2["means"].shape[0] == 12 and all(torch.isfinite(v).all() for v in p2.values())


# ------------------------------------------------------------------------------ composition
def test_seedsplit_is_composed_not_copied():
    # No behaviour is defined on Seed+Split itself: it holds the two operators, in the order they run.
    own = {k for k, v in vars(SeedSplitStrategy).items() if callable(v) and not k.startswith("__")}
    assert own == set()
    assert SeedSplitStrategy.__mro__[1:3] == (ExplorationStrategy, DefaultStrategy)
    s = SeedSplitStrategy()
    assert [(name, type(op)) for name, op in s.operators()] == [("splitting", RandomSplitting), ("seeding", RandomSeeding)]
    assert [(name, type(op)) for name, op in SeedingStrategy().operators()] == [("seeding", RandomSeeding)]
    assert DefaultStrategy().size_prune_factor(0) == 0.1 and not hasattr(DefaultStrategy(), "operators")


def test_seedsplit_does_both_and_counts_them():
    gen = torch.Generator().manual_seed(0)
    params = make_gaussians(40, gen)
    s = SeedSplitStrategy(seeding=RandomSeeding(n_seed=5, every=10), splitting=RandomSplitting(n_split=3, every=1), prune_opa=0.0, grow_grad2d=1e9, **WINDOW)
    state = s.initialize_state()
    history = _run(s, params, make_optimizers(params), state, range(3, 21), gen)
    assert sum(c["random_split"] for c in history) == 3 * 18
    assert sum(c["seeded"] for c in history) == 10
    assert params["means"].shape[0] == 40 + 3 * 18 + 10
    # Fresh seeds are added after the split of their step, so they are the last rows.
    assert torch.equal(state["stats"][SEED_FLAG][-5:], torch.ones(5))


def test_every_strategy_handles_all_pruned():
    gen = torch.Generator().manual_seed(0)
    for cls in (SeedingStrategy, SplittingStrategy, SeedSplitStrategy):
        params = make_gaussians(12, gen)
        with torch.no_grad():
            params["opacities"].fill_(-30.0)
        operators = {"seeding": RandomSeeding(n_seed=3, every=10), "splitting": RandomSplitting(n_split=2, every=1)}
        s = cls(**{name: op for name, op in operators.items() if name in {f.name for f in fields(cls)}}, **WINDOW)
        state = s.initialize_state()
        # Step 10: the random split runs after the prune emptied the set; seeding finds no box.
        _run(s, params, make_optimizers(params), state, [10, 11, 20], gen)
        assert params["means"].shape[0] == 0, cls


# ------------------------------------------------------------------------------ config
def test_setup_resolves_budget_fields():
    schedule = ScheduleConfig().resolve(3000)
    paper = SeedSplitStrategy().setup(schedule)
    assert (paper.seeding.n_seed, paper.seeding.every, paper.splitting.n_split, paper.splitting.every) == (
        20, schedule.refine_every, 20, 1)
    own = SeedSplitStrategy(seeding=RandomSeeding(n_seed=50)).setup(schedule)
    assert own.seeding.n_seed == 50 and own.seeding.every == schedule.refine_every
    # the operator configs the user passed are not changed in place (setup returns copies)
    mine = SeedSplitStrategy()
    mine.setup(schedule)
    assert mine.seeding.n_seed is None and mine.splitting.every is None
    with pytest.raises(StrategyError, match=r"seeding\.n_seed.*setup"):
        SeedingStrategy(**WINDOW).step_post_backward({}, {}, {}, 1, {})
    with pytest.raises(ValueError, match="unknown exploration budget"):
        SeedSplitStrategy(budget="huge")


@pytest.mark.parametrize("name", [k for k, v in BUDGET_PRESETS.items() if v is not None])
def test_cpu_budgets_keep_paper_ratios(name):
    schedule = ScheduleConfig().resolve(3000)
    b = resolve_budget(name, schedule.refine_start, schedule.refine_stop, schedule.refine_every)
    final = BUDGET_PRESETS[name]
    window = schedule.refine_stop - schedule.refine_start
    total_splits = b.n_split * (window // b.split_every)
    total_seeds = b.n_seed * (window // b.seed_every)
    for total, fraction in ((total_splits, SPLIT_FRACTION), (total_seeds, SEED_FRACTION)):
        target = round(fraction * final)
        assert abs(total - target) <= max(1.0, 0.05 * target), (total, target)
    assert b.split_every <= 50  # spread over the window, not lumped into a few events
    assert b.seed_every % schedule.refine_every == 0  # seeding happens on densification steps


def test_paper_budget_matches_paper_totals():
    # The paper's run: window 500..15000, interval 100 -> 290k splits and ~2.9k seeds.
    b = resolve_budget("paper", 500, 15000, 100)
    assert b.n_split * 14500 == 290_000
    assert b.n_seed * (14500 // b.seed_every) == 2900
    assert math.isclose(2900 / 1_500_000, SEED_FRACTION, rel_tol=0.05)
    with pytest.raises(ValueError):
        scaled_budget(0, 0, 10, 1)
