"""The gsplat strategies of exploregs_plugin.integrations.gsplat on synthetic Gaussians (CPU).

Each training step renders nothing: a fake ``info`` carries 2D means that depend on the 3D means
(so ``means2d.grad`` exists), radii in gsplat 1.5's layout ([C, N, 2]) or the older one ([C, N]),
packed or not. Before every ``step_post_backward`` the set is deep-copied and a plain gsplat
DefaultStrategy with the same settings runs on the copy with the same info and the same global
random state: what it did is gsplat's share, and the rest must be exactly our operators' rows.
"""

from __future__ import annotations

import copy
import dataclasses
import importlib
import math
import sys

import pytest
import torch
from torch import Tensor

pytest.importorskip("gsplat", reason="gsplat is not installed (pip install gsplat==1.5.3)")
from gsplat.strategy import DefaultStrategy as GsplatDefaultStrategy, MCMCStrategy  # noqa: E402

from exploregs_plugin.integrations import gsplat as integ  # noqa: E402
from exploregs_plugin.strategies import StrategyError  # noqa: E402

W = H = 64
CAMERAS = 2
SCHEDULE = dict(refine_start_iter=1, refine_stop_iter=7, refine_every=3, reset_every=4, pause_refine_after_reset=0)
STEPS = range(8)
SPLIT_STEPS = {2, 3, 4, 5, 6}  # refine_start_iter < step < refine_stop_iter
SEED_STEPS = {3, 6}  # where gsplat refines; step 6 also prunes by world size (6 > reset_every)
SH_REST = 15


@pytest.fixture(autouse=True)
def one_thread():
    """Tensors of a few hundred rows: one thread is fastest, and much faster than two on a CPU
    that another process keeps busy."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


# ------------------------------------------------------------------------------ synthetic scene
def make_params(layout: str, n: int = 300, seed: int = 0):
    """Gaussians spread over every threshold of gsplat's refine, in gsplat's or nerfstudio's
    layout, with one Adam per parameter (as simple_trainer builds them)."""
    g = torch.Generator().manual_seed(seed)

    def u(*shape):
        return torch.rand(*shape, generator=g)

    opacity_logits = u(n) * 10 - 7  # sigmoid from 0.001 to 0.95: about 17% below prune_opa
    rows = {
        "means": u(n, 3) * 2 - 1,
        "scales": math.log(0.003) + u(n, 3) * math.log(100.0),  # 0.003..0.3 x scene scale
        "quats": torch.randn(n, 4, generator=g),
    }
    if layout == "gsplat":
        rows |= {"opacities": opacity_logits, "sh0": torch.randn(n, 1, 3, generator=g),
                 "shN": 0.1 * torch.randn(n, SH_REST, 3, generator=g)}
    else:  # nerfstudio's splatfacto
        rows |= {"features_dc": torch.randn(n, 3, generator=g),
                 "features_rest": 0.1 * torch.randn(n, SH_REST, 3, generator=g),
                 "opacities": opacity_logits[:, None]}
    params = torch.nn.ParameterDict({k: torch.nn.Parameter(v) for k, v in rows.items()})
    optimizers = {k: torch.optim.Adam([{"params": p, "lr": 1e-3, "name": k}], eps=1e-15) for k, p in params.items()}
    return params, optimizers


def single_radius(pairs: Tensor) -> Tensor:
    """The pre-1.5 layout of a radius pair: the larger value, 0 when culled on either axis."""
    return torch.where((pairs > 0).all(-1), pairs.max(-1).values, torch.zeros_like(pairs[..., 0]))


def fake_render(params, step: int, radii: str, packed: bool):
    """(info, the same info with radii in the installed gsplat's layout, loss)."""
    n = params["means"].shape[0]
    g = torch.Generator().manual_seed(1000 + step)
    pairs = torch.randint(0, 6, (CAMERAS, n, 2), generator=g, dtype=torch.int32)  # 0 on an axis: culled
    sizes = torch.exp(torch.empty(CAMERAS, n, 2).uniform_(math.log(3e-7), math.log(3e-5), generator=g))
    weights = sizes * torch.where(torch.rand(CAMERAS, n, 2, generator=g) < 0.5, -1.0, 1.0)
    means2d = (params["means"][None, :, :2] * W / 2 + W / 2).expand(CAMERAS, n, 2)  # [C, N, 2]
    ids = None
    if packed:
        visible = (pairs > 0).all(-1)
        ids = torch.where(visible)[1]
        means2d, weights, pairs = means2d[visible], weights[visible], pairs[visible]
    single = single_radius(pairs)
    info = {"means2d": means2d, "radii": pairs if radii == "pairs" else single, "width": W, "height": H,
            "n_cameras": CAMERAS, "gaussian_ids": ids}
    installed = {**info, "radii": pairs if integ.RADII_PAIRS else single}
    # every parameter gets a gradient, so every Adam state exists
    loss = (means2d * weights).sum() + 1e-4 * sum((p**2).sum() for p in params.values())
    return info, installed, loss


def gsplat_reference(strategy, params, optimizers, state, step, info, packed):
    """Plain gsplat DefaultStrategy (same settings and prune threshold) on a deep copy."""
    ref_params, ref_optimizers = copy.deepcopy((params, optimizers))
    ref_state = {k: v.clone() if isinstance(v, Tensor) else v for k, v in state.items() if k != "generator"}
    settings = {f.name: getattr(strategy, f.name) for f in dataclasses.fields(GsplatDefaultStrategy)}
    plain = GsplatDefaultStrategy(**{**settings, "prune_scale3d": strategy.prune_scale3d_at(step)})
    torch.manual_seed(step)  # gsplat's split draws from the global generator
    plain.step_post_backward(ref_params, ref_optimizers, ref_state, step, info, packed=packed)
    return ref_params, ref_optimizers, ref_state


def train(strategy, layout="gsplat", radii="pairs", packed=False, check=None, params=None):
    """Run STEPS; ``check(step, before, reference, after, counts)`` is called after every step."""
    if params is None:
        params, optimizers = make_params(layout)
    else:
        params, optimizers = params
    state = strategy.initialize_state(scene_scale=1.0)
    strategy.check_sanity(params, optimizers)
    for step in STEPS:
        info, installed, loss = fake_render(params, step, radii, packed)
        strategy.step_pre_backward(params, optimizers, state, step, info)
        loss.backward()
        for opt in optimizers.values():
            opt.step()
            opt.zero_grad(set_to_none=True)
        n_before = params["means"].shape[0]
        reference = gsplat_reference(strategy, params, optimizers, state, step, installed, packed) if check else None
        torch.manual_seed(step)
        counts = strategy.step_post_backward(params, optimizers, state, step, info, packed=packed)
        if check:
            check(step, n_before, reference, (params, optimizers, state), counts)
    return params, optimizers, state


# ------------------------------------------------------------------------------ alignment check
def _moments(optimizers, params, key):
    assert optimizers[key].param_groups[0]["params"][0] is params[key]
    st = optimizers[key].state[params[key]]
    return st["exp_avg"], st["exp_avg_sq"]


def _row_keys(params, optimizers) -> Tensor:
    """Every parameter and moment of each row, flattened: identifies a row that was kept."""
    parts = []
    for key in params:
        parts += [params[key].detach(), *_moments(optimizers, params, key)]
    return torch.cat([p.reshape(p.shape[0], -1) for p in parts], dim=1)


def assert_exploration_rows(strategy, step, n_before, reference, after, counts):
    """After gsplat's rows: the kept rows (same values, moments and statistics), the children of
    the random split (copies, scales / 1.6, zero moments, parents' statistics), then the seeds."""
    ref_params, ref_opts, ref_state = reference
    params, optimizers, state = after
    splits = getattr(strategy, "n_split", 0) if step in SPLIT_STEPS else 0
    seeds = getattr(strategy, "n_seed", 0) if step in SEED_STEPS else 0
    assert counts.get("random_split", 0) == splits and counts.get("seeded", 0) == seeds
    n_ref, n = ref_params["means"].shape[0], params["means"].shape[0]
    if step in SEED_STEPS:
        assert n_ref != n_before  # gsplat's own refine did something
    assert n == n_ref + splits + seeds

    row_stats = sorted(k for k, v in ref_state.items() if isinstance(v, Tensor))
    assert row_stats == sorted(k for k, v in state.items() if isinstance(v, Tensor))
    assert {"grad2d", "count"} <= set(row_stats)
    for key in params:
        assert all(m.shape == params[key].shape for m in _moments(optimizers, params, key)), key
    for key in row_stats:
        assert state[key].shape[0] == n, key

    keep = n_ref - splits
    ref_rows = {row.numpy().tobytes(): i for i, row in enumerate(_row_keys(ref_params, ref_opts))}
    assert len(ref_rows) == n_ref  # every reference row is distinct
    idx = torch.tensor([ref_rows[row.numpy().tobytes()] for row in _row_keys(params, optimizers)[:keep]])
    assert (idx.diff() > 0).all()  # kept rows keep their order
    parents = torch.ones(n_ref, dtype=torch.bool)
    parents[idx] = False
    assert int(parents.sum()) == splits
    children = slice(keep, keep + 2 * splits)
    for key in params:
        p, ref = params[key].detach(), ref_params[key].detach()[parents]
        if key == "scales":
            assert torch.allclose(p[children], (ref - math.log(1.6)).repeat(2, 1))
        elif key != "means":
            assert torch.equal(p[children], ref.repeat(2, *[1] * (ref.dim() - 1))), key
        for moment in _moments(optimizers, params, key):
            assert not moment[keep:].any(), key  # children and seeds start at zero
    for key in row_stats:
        assert torch.equal(state[key][:keep], ref_state[key][idx]), key
        assert torch.equal(state[key][children], ref_state[key][parents].repeat(2)), key
        assert not state[key][keep + 2 * splits:].any(), key

    if seeds:
        assert_seeds(params, seeds)


def assert_seeds(params, seeds: int) -> None:
    """The last rows are seeds: in the box of the other centres, seed_rows' rule, the layout's shapes."""
    means = params["means"].detach()
    lo, hi = means[:-seeds].min(0).values, means[:-seeds].max(0).values
    assert ((means[-seeds:] >= lo) & (means[-seeds:] <= hi)).all()
    opacity = torch.sigmoid(params["opacities"].detach()[-seeds:])
    assert ((opacity >= 0.2 - 1e-6) & (opacity <= 0.7 + 1e-6)).all()
    scales = params["scales"].detach()[-seeds:]
    assert torch.equal(scales, scales[:, :1].expand(-1, 3))  # isotropic
    rest = params["shN"] if "shN" in params else params["features_rest"]
    assert not rest[-seeds:].any()
    dc = params["sh0"] if "sh0" in params else params["features_dc"]
    assert dc.shape[1:] == dc[-seeds:].shape[1:] and (dc[-seeds:].abs() <= 0.5 / 0.28209479 + 1e-4).all()


# ------------------------------------------------------------------------------ tests
CASES = [
    (integ.SeedSplitStrategy, "gsplat", "pairs", False),
    (integ.SeedSplitStrategy, "gsplat", "pairs", True),
    (integ.SeedSplitStrategy, "gsplat", "single", False),
    (integ.SeedSplitStrategy, "gsplat", "single", True),
    (integ.SeedSplitStrategy, "nerfstudio", "single", False),
    (integ.SeedSplitStrategy, "nerfstudio", "pairs", True),
    (integ.SeedStrategy, "gsplat", "pairs", False),
    (integ.SplitStrategy, "nerfstudio", "single", False),
]


@pytest.mark.parametrize("cls,layout,radii,packed", CASES)
def test_rows_moments_and_gsplat_state_stay_aligned(cls, layout, radii, packed):
    strategy = cls(**SCHEDULE, seed=3)
    assert isinstance(strategy, GsplatDefaultStrategy)
    params, _, _ = train(strategy, layout, radii, packed,
                         check=lambda *args: assert_exploration_rows(strategy, *args))
    assert params["means"].shape[0] > 300


def test_gsplat_screen_size_state_radii_is_aligned_too():
    # refine_scale2d_stop_iter > 0 makes gsplat keep a third per-Gaussian tensor, state["radii"]
    strategy = integ.SeedSplitStrategy(**SCHEDULE, refine_scale2d_stop_iter=100, seed=1)
    filled = []

    def check(step, n_before, reference, after, counts):
        assert_exploration_rows(strategy, step, n_before, reference, after, counts)
        filled.append(bool(after[2]["radii"].any()))  # gsplat zeroes it after each refine

    train(strategy, check=check)
    assert any(filled)


def _run(strategy, **kwargs):
    torch.manual_seed(0)
    params, _, state = train(strategy, **kwargs)
    return {k: v.detach().clone() for k, v in params.items()}, state


def test_a_fixed_seed_repeats_the_run_and_the_radii_layout_does_not_matter():
    first, _ = _run(integ.SeedSplitStrategy(**SCHEDULE, seed=5))
    again, _ = _run(integ.SeedSplitStrategy(**SCHEDULE, seed=5))
    single, _ = _run(integ.SeedSplitStrategy(**SCHEDULE, seed=5), radii="single")
    other, _ = _run(integ.SeedSplitStrategy(**SCHEDULE, seed=6))
    for run in (again, single):
        assert first.keys() == run.keys() and all(torch.equal(first[k], run[k]) for k in first)
    assert first["means"].shape != other["means"].shape or not torch.equal(first["means"], other["means"])


def test_seeding_relaxes_gsplat_world_size_prune_only_during_its_refine():
    # step 6 is after the first reset interval, so gsplat prunes by world size (0.1 x scene scale)
    seeding, splitting = (cls(**SCHEDULE, seed=0) for cls in (integ.SeedStrategy, integ.SplitStrategy))
    assert seeding.prune_scale3d_at(6) == 10.0 and seeding.prune_scale3d == 0.1
    assert splitting.prune_scale3d_at(6) == 0.1
    assert integ.SeedStrategy(**SCHEDULE, n_seed=0).prune_scale3d_at(6) == 0.1

    def largest(params, skip=0):
        scales = params["scales"].detach()[: params["scales"].shape[0] - skip]
        return torch.exp(scales).max(-1).values

    seeded, _ = _run(seeding)
    split, _ = _run(splitting)
    assert int((largest(seeded, skip=20) > 0.1).sum()) > 20  # survived step 6's prune
    assert not (largest(split) > 0.101).any()  # pruned at 6 as plain gsplat does (0.1, one Adam step after)
    assert seeding.prune_scale3d == 0.1

    params, optimizers = make_params("gsplat")
    state = seeding.initialize_state()
    with pytest.raises(AssertionError):  # gsplat's own check fails inside the relaxed block
        seeding.step_post_backward(params, optimizers, state, 6, {"radii": torch.ones(1, 300, 2)})
    assert seeding.prune_scale3d == 0.1


def test_parameters_seeds_cannot_fill_fail_in_one_line():
    params, optimizers = make_params("gsplat", n=50)
    params["features"] = torch.nn.Parameter(torch.zeros(50, 8))  # simple_trainer's appearance model
    optimizers["features"] = torch.optim.Adam([params["features"]])
    with pytest.raises(StrategyError, match=r"cannot fill parameters \['features'\]") as err:
        integ.SeedSplitStrategy(**SCHEDULE).check_sanity(params, optimizers)
    assert "\n" not in str(err.value)
    with pytest.raises(StrategyError, match="features"):  # also without check_sanity, at a seeding step
        integ.SeedStrategy(**SCHEDULE).add_seeds(params, optimizers, {"scene_scale": 1.0}, torch.Generator())
    integ.SplitStrategy(**SCHEDULE).check_sanity(params, optimizers)  # splitting copies any attribute

    params, _ = make_params("nerfstudio", n=5)
    params["features_dc"] = torch.nn.Parameter(torch.zeros(5, 4))
    rows = {"sh0": torch.zeros(2, 1, 3)}
    with pytest.raises(StrategyError, match=r"'features_dc' has rows of shape \(4,\)"):
        integ.seed_params({**rows, "means": torch.zeros(2, 3), "scales": torch.zeros(2, 3), "quats": torch.zeros(2, 4),
                           "opacities": torch.zeros(2), "shN": torch.zeros(2, SH_REST, 3)}, params)


def test_radii_layout_converts_between_gsplat_versions():
    pairs = torch.tensor([[[3, 4], [0, 2], [5, 0], [1, 1]]], dtype=torch.int32)  # [C=1, N=4, 2]
    single = integ.radii_layout(pairs, packed=False, pairs=False)
    assert torch.equal(single, torch.tensor([[4, 0, 0, 1]], dtype=torch.int32))
    back = integ.radii_layout(single, packed=False, pairs=True)
    assert back.shape == (1, 4, 2) and torch.equal((back > 0).all(-1), (pairs > 0).all(-1))
    assert integ.radii_layout(pairs, packed=False, pairs=True) is pairs
    assert integ.radii_layout(pairs[0], packed=True, pairs=False).shape == (4,)
    assert integ.radii_layout(single[0], packed=True, pairs=True).shape == (4, 2)
    with pytest.raises(StrategyError, match="info\\['radii'\\] has shape \\(4,\\)"):
        integ.radii_layout(single[0], packed=False, pairs=True)


def test_from_default_keeps_gsplat_settings_and_fields_are_checked():
    splatfacto_like = GsplatDefaultStrategy(prune_opa=0.1, refine_every=50, pause_refine_after_reset=130, absgrad=True)
    s = integ.SeedSplitStrategy.from_default(splatfacto_like, seed=4, n_split=7)
    assert isinstance(s, GsplatDefaultStrategy)
    assert (s.prune_opa, s.refine_every, s.pause_refine_after_reset, s.absgrad) == (0.1, 50, 130, True)
    assert (s.seed, s.n_split, s.n_seed, s.split_every, s.seed_prune_scale3d) == (4, 7, 20, 1, 10.0)
    with pytest.raises(StrategyError, match="needs a gsplat DefaultStrategy, got MCMCStrategy"):
        integ.SeedStrategy.from_default(MCMCStrategy())
    for bad in ({"n_seed": -1}, {"n_split": -1}, {"split_every": 0}, {"seed_prune_scale3d": 0.0}):
        with pytest.raises(StrategyError):
            integ.SeedSplitStrategy(**bad)


def test_outside_the_refine_window_only_gsplat_runs():
    strategy = integ.SeedSplitStrategy(**SCHEDULE)
    params, optimizers = make_params("gsplat", n=40)
    state = strategy.initialize_state()
    info, _, loss = fake_render(params, 7, "pairs", False)
    strategy.step_pre_backward(params, optimizers, state, 7, info)
    loss.backward()
    assert strategy.step_post_backward(params, optimizers, state, 7, info) == {}
    assert params["means"].shape[0] == 40 and state["generator"] is None


def test_import_without_gsplat_is_one_clear_line(monkeypatch):
    monkeypatch.setitem(sys.modules, "gsplat", None)
    monkeypatch.delitem(sys.modules, "exploregs_plugin.integrations.gsplat")
    with pytest.raises(ImportError, match=r"pip install gsplat==1\.5\.3") as err:
        importlib.import_module("exploregs_plugin.integrations.gsplat")
    assert "\n" not in str(err.value)
