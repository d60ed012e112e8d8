"""Our exploration operators behind gsplat's strategy API (exploregs_plugin.integrations.into_gsplat)
on synthetic Gaussians (CPU).

Each training step renders nothing: a fake ``info`` carries 2D means that depend on the 3D means
(so ``means2d.grad`` exists), radii in gsplat 1.5's layout ([C, N, 2]) or the older one ([C, N]),
packed or not. Two references:

- gsplat's share: before every ``step_post_backward`` the set is deep-copied and a plain gsplat
  DefaultStrategy with the same settings runs on the copy with the same info and global random
  state; the rest must be exactly our operators' rows;
- eg-train's: the strategy of the same name (``Strategy.step_post_backward`` with our
  observations) runs in lockstep from the same Gaussians and generator seed, and every parameter,
  Adam moment and per-Gaussian statistic must be the same after every step.
"""

from __future__ import annotations

import collections
import copy
import dataclasses
import importlib
import math
import sys

import pytest
import torch
from torch import Tensor

pytest.importorskip("gsplat", reason="gsplat is not installed (pip install gsplat==1.5.3)")
from gsplat.strategy import DefaultStrategy as GsDefault, MCMCStrategy as GsMCMC  # noqa: E402

import gsplat.strategy.ops  # noqa: E402

from exploregs_plugin.cameras import Camera  # noqa: E402
from exploregs_plugin.integrations import into_gsplat as integ  # noqa: E402
from exploregs_plugin.integrations.gsplat_info import camera_centers, observations, radii_layout  # noqa: E402
from exploregs_plugin.schedule import Schedule  # noqa: E402
from exploregs_plugin.strategies import (  # noqa: E402
    MCMCStrategy,
    Operator,
    PositionNoise,
    RandomSeeding,
    RandomSplitting,
    RayPerturbationStrategy,
    SeedingStrategy,
    SeedSplitStrategy,
    SplittingStrategy,
    StrategyError,
    row_ops,
)
from exploregs_plugin.strategies.observation import ViewObservation  # noqa: E402
from exploregs_plugin.strategies.relocation import relocation_update  # noqa: E402
from exploregs_plugin.strategies.seeding import SEED_FLAG, SEED_SEEN  # noqa: E402
from exploregs_plugin.strategies.synthetic import synthetic_views  # noqa: E402

W = H = 64
CAMERAS = 2
SCHEDULE = dict(refine_start_iter=1, refine_stop_iter=7, refine_every=3, reset_every=4, pause_refine_after_reset=0)
STEPS = range(8)
SPLIT_STEPS = {2, 3, 4, 5, 6}  # refine_start_iter < step < refine_stop_iter
SEED_STEPS = {3, 6}  # where gsplat refines; step 6 also prunes by world size (6 > reset_every)
SH_REST = 15
GSPLAT_STATS = ("grad2d", "count", "radii")


pytestmark = pytest.mark.usefixtures("one_thread")


# ------------------------------------------------------------------------------ synthetic scene
def make_params(layout: str, n: int = 300, seed: int = 0):
    """Gaussians spread over every threshold of gsplat's refine, in gsplat's or nerfstudio's
    layout (the same values in both), with one Adam per parameter (as simple_trainer builds them)."""
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


def viewmat(center, angle: float) -> Tensor:
    """World-to-camera [4, 4] of a camera at ``center`` turned by ``angle`` about y: [R | -R c]."""
    c, s_ = math.cos(angle), math.sin(angle)
    rot = torch.tensor([[c, 0.0, s_], [0.0, 1.0, 0.0], [-s_, 0.0, c]])
    out = torch.eye(4)
    out[:3, :3], out[:3, 3] = rot, -rot @ torch.tensor(center)
    return out


VIEWMATS = torch.stack([viewmat((0.3, -0.2, -3.0), 0.2), viewmat((2.5, 0.5, 0.0), -1.2)])  # [C, 4, 4]


def native_centers() -> list[Tensor]:
    """The cameras' centres as our pipeline computes them (Camera.camera_center)."""
    return [Camera(v, torch.eye(3), W, H).camera_center for v in VIEWMATS]


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
    ids = cams = None
    if packed:
        visible = (pairs > 0).all(-1)
        cams, ids = torch.where(visible)
        means2d, weights, pairs = means2d[visible], weights[visible], pairs[visible]
    single = single_radius(pairs)
    info = {"means2d": means2d, "radii": pairs if radii == "pairs" else single, "width": W, "height": H,
            "n_cameras": CAMERAS, "camera_ids": cams, "gaussian_ids": ids, "viewmats": VIEWMATS}
    installed = {**info, "radii": pairs if integ.RADII_PAIRS else single}
    # every parameter gets a gradient, so every Adam state exists
    loss = (means2d * weights).sum() + 1e-4 * sum((p**2).sum() for p in params.values())
    return info, installed, loss


def adam_step(optimizers) -> None:
    for opt in optimizers.values():
        opt.step()
        opt.zero_grad(set_to_none=True)


def gsplat_reference(strategy, params, optimizers, state, step, info, packed):
    """Plain gsplat DefaultStrategy (same settings and prune threshold) on a deep copy."""
    ref_params, ref_optimizers = copy.deepcopy((params, optimizers))
    ref_state = {k: v.clone() if isinstance(v, Tensor) else v for k, v in state.items() if k != "generator"}
    settings = {f.name: getattr(strategy, f.name) for f in dataclasses.fields(GsDefault)}
    threshold = strategy.size_prune_factor(strategy.resolved_operators(CAMERAS), step)
    plain = GsDefault(**{**settings, "prune_scale3d": threshold})
    torch.manual_seed(step)  # gsplat's split draws from the global generator
    plain.step_post_backward(ref_params, ref_optimizers, ref_state, step, info, packed=packed)
    return ref_params, ref_optimizers, ref_state


def train(strategy, layout="gsplat", radii="pairs", packed=False, check=None, params=None):
    """Run STEPS; ``check(step, before, reference, after, counts)`` is called after every step."""
    params, optimizers = make_params(layout) if params is None else params
    state = strategy.initialize_state(scene_scale=1.0)
    strategy.check_sanity(params, optimizers)
    for step in STEPS:
        info, installed, loss = fake_render(params, step, radii, packed)
        strategy.step_pre_backward(params, optimizers, state, step, info)
        loss.backward()
        adam_step(optimizers)
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
    operators = dict(strategy.resolved_operators(CAMERAS))
    splits = operators["splitting"].n_split if "splitting" in operators and step in SPLIT_STEPS else 0
    seeds = operators["seeding"].n_seed if "seeding" in operators and step in SEED_STEPS else 0
    assert counts.get("random_split", 0) == splits and counts.get("seeded", 0) == seeds
    assert counts.get("seeds_pruned", 0) == 0  # seeds start at opacity >= 0.2, above probation's 0.05
    n_ref, n = ref_params["means"].shape[0], params["means"].shape[0]
    if step in SEED_STEPS:
        assert n_ref != n_before  # gsplat's own refine did something
    assert n == n_ref + splits + seeds

    for key in (SEED_FLAG, SEED_SEEN):  # made by this step's first seeds: 0 for every earlier row
        if key in state and key not in ref_state:
            ref_state[key] = torch.zeros(n_ref)
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
    # gsplat's statistics and the seed flags are inherited; seed_seen counts this step's views
    # before gsplat's step (eg-train's order), which the reference did not see: the lockstep tests
    for key in set(row_stats) - {SEED_SEEN}:
        assert torch.equal(state[key][:keep], ref_state[key][idx]), key
        assert torch.equal(state[key][children], ref_state[key][parents].repeat(2)), key
        assert torch.equal(state[key][keep + 2 * splits:], torch.full((seeds,), float(key == SEED_FLAG))), key

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


# ------------------------------------------------------------------------------ gsplat's share + ours
CASES = [
    (integ.GsplatSeedSplitStrategy, "gsplat", "pairs", False),
    (integ.GsplatSeedSplitStrategy, "gsplat", "pairs", True),
    (integ.GsplatSeedSplitStrategy, "gsplat", "single", False),
    (integ.GsplatSeedSplitStrategy, "gsplat", "single", True),
    (integ.GsplatSeedSplitStrategy, "nerfstudio", "single", False),
    (integ.GsplatSeedSplitStrategy, "nerfstudio", "pairs", True),
    (integ.GsplatSeedStrategy, "gsplat", "pairs", False),
    (integ.GsplatSplitStrategy, "nerfstudio", "single", False),
]


@pytest.mark.parametrize("cls,layout,radii,packed", CASES)
def test_rows_moments_and_gsplat_state_stay_aligned(cls, layout, radii, packed):
    strategy = cls(**SCHEDULE, seed=3)
    assert isinstance(strategy, GsDefault)
    params, _, _ = train(strategy, layout, radii, packed,
                         check=lambda *args: assert_exploration_rows(strategy, *args))
    assert params["means"].shape[0] > 300


def test_gsplat_screen_size_state_radii_is_aligned_too():
    # refine_scale2d_stop_iter > 0 makes gsplat keep a third per-Gaussian tensor, state["radii"]
    strategy = integ.GsplatSeedSplitStrategy(**SCHEDULE, refine_scale2d_stop_iter=100, seed=1)
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
    first, _ = _run(integ.GsplatSeedSplitStrategy(**SCHEDULE, seed=5))
    again, _ = _run(integ.GsplatSeedSplitStrategy(**SCHEDULE, seed=5))
    single, _ = _run(integ.GsplatSeedSplitStrategy(**SCHEDULE, seed=5), radii="single")
    other, _ = _run(integ.GsplatSeedSplitStrategy(**SCHEDULE, seed=6))
    for run in (again, single):
        assert first.keys() == run.keys() and all(torch.equal(first[k], run[k]) for k in first)
    assert first["means"].shape != other["means"].shape or not torch.equal(first["means"], other["means"])


def test_seeding_relaxes_gsplat_world_size_prune_only_during_its_refine():
    # step 6 is after the first reset interval, so gsplat prunes by world size (0.1 x scene scale)
    seeding, splitting = (cls(**SCHEDULE, seed=0) for cls in (integ.GsplatSeedStrategy, integ.GsplatSplitStrategy))
    assert seeding.size_prune_factor(seeding.resolved_operators(), 6) == 10.0 and seeding.prune_scale3d == 0.1
    assert splitting.size_prune_factor(splitting.resolved_operators(), 6) == 0.1
    off = integ.GsplatSeedStrategy(**SCHEDULE, seeding=RandomSeeding(n_seed=0))
    assert off.size_prune_factor(off.resolved_operators(), 6) == 0.1

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
    info, _, _ = fake_render(params, 6, "pairs", False)
    del info["gaussian_ids"]  # gsplat's own check fails inside the relaxed block
    with pytest.raises(AssertionError, match="gaussian_ids is required"):
        seeding.step_post_backward(params, optimizers, state, 6, info)
    assert seeding.prune_scale3d == 0.1 and seeding._step is None


def test_parameters_seeds_cannot_fill_fail_in_one_line():
    params, optimizers = make_params("gsplat", n=50)
    params["features"] = torch.nn.Parameter(torch.zeros(50, 8))  # simple_trainer's appearance model
    optimizers["features"] = torch.optim.Adam([params["features"]])
    with pytest.raises(StrategyError, match=r"cannot fill parameters \['features'\]") as err:
        integ.GsplatSeedSplitStrategy(**SCHEDULE).check_sanity(params, optimizers)
    assert "\n" not in str(err.value)
    strategy = integ.GsplatSeedStrategy(**SCHEDULE)
    info, _, _ = fake_render(params, 3, "pairs", False)
    with pytest.raises(StrategyError, match="features"):  # also without check_sanity, at a step
        strategy.step_post_backward(params, optimizers, strategy.initialize_state(), 3, info)
    integ.GsplatSplitStrategy(**SCHEDULE).check_sanity(params, optimizers)  # splitting copies any attribute

    params, optimizers = make_params("nerfstudio", n=5)
    params["features_dc"] = torch.nn.Parameter(torch.zeros(5, 4))
    with pytest.raises(StrategyError, match=r"'features_dc' has rows of shape \(4,\); ExploreGS reads sh0 rows of "
                                            r"shape \(1, 3\)"):
        integ.GsplatSplitStrategy(**SCHEDULE).check_sanity(params, optimizers)


def test_our_layout_renames_and_reshapes_nerfstudios_parameters_with_their_moments():
    params, optimizers = make_params("nerfstudio", n=20)
    _, _, loss = fake_render(params, 0, "pairs", False)
    loss.backward()
    adam_step(optimizers)
    before = {k: (p.detach().clone(), *[m.clone() for m in _moments(optimizers, params, k)]) for k, p in params.items()}
    with integ.our_layout(params, optimizers) as (ours, ours_opt):
        assert sorted(ours) == sorted(integ.SEEDED)
        assert (ours["sh0"].shape, ours["opacities"].shape) == ((20, 1, 3), (20,))
        assert ours_opt["sh0"] is optimizers["features_dc"] and _moments(ours_opt, ours, "sh0")[0].shape == (20, 1, 3)
        row_ops.remove(ours, ours_opt, {}, torch.arange(20) < 5)  # an op inside the block
    for key, (value, *moments) in before.items():
        assert params[key].shape == (15, *value.shape[1:]) and torch.equal(params[key].detach(), value[5:])
        for mine, old in zip(_moments(optimizers, params, key), moments):  # the Adam follows its parameter
            assert torch.equal(mine, old[5:]), key
    with pytest.raises(RuntimeError, match="inside"), integ.our_layout(params, optimizers):
        raise RuntimeError("inside")
    assert params["opacities"].shape == (15, 1) and params["features_dc"].shape == (15, 3)


def test_radii_layout_converts_between_gsplat_versions():
    pairs = torch.tensor([[[3, 4], [0, 2], [5, 0], [1, 1]]], dtype=torch.int32)  # [C=1, N=4, 2]
    single = radii_layout(pairs, packed=False, pairs=False)
    assert torch.equal(single, torch.tensor([[4, 0, 0, 1]], dtype=torch.int32))
    back = radii_layout(single, packed=False, pairs=True)
    assert back.shape == (1, 4, 2) and torch.equal((back > 0).all(-1), (pairs > 0).all(-1))
    assert radii_layout(pairs, packed=False, pairs=True) is pairs
    assert radii_layout(pairs[0], packed=True, pairs=False).shape == (4,)
    assert radii_layout(single[0], packed=True, pairs=True).shape == (4, 2)
    with pytest.raises(StrategyError, match="info\\['radii'\\] has shape \\(4,\\)"):
        radii_layout(single[0], packed=False, pairs=True)


@pytest.mark.parametrize("radii,packed", [("pairs", False), ("single", True)])
def test_observations_are_gsplats_info_view_by_view(radii, packed):
    params, _ = make_params("gsplat", n=40)
    info, _, loss = fake_render(params, 2, radii, packed)
    info["means2d"].retain_grad()
    loss.backward()
    full, _, full_loss = fake_render(params, 2, "pairs", False)  # the same render, unpacked with pairs
    full["means2d"].retain_grad()
    full_loss.backward()
    views = observations(info, 40, packed)
    assert len(views) == CAMERAS
    for c, view in enumerate(views):
        assert (view.width, view.height, view.n_cameras, view.num_gaussians) == (W, H, CAMERAS, 40)
        visible = (full["radii"][c] > 0).all(-1)
        assert torch.equal(view.visible(), visible)
        grad = full["means2d"].grad[c]
        assert torch.equal(view.screen_gradient()[visible], grad[visible])
        hidden = torch.zeros_like(grad[~visible]) if packed else grad[~visible]  # packed: nothing for them
        assert torch.equal(view.screen_gradient()[~visible], hidden)
        assert torch.equal(view.camera_center, native_centers()[c])  # Camera.camera_center's bits
    c2w = torch.linalg.inv(VIEWMATS)
    assert torch.allclose(camera_centers({"camtoworlds": c2w}), torch.stack(native_centers()), atol=1e-5)
    no_camera = {k: v for k, v in info.items() if k != "viewmats"}
    assert all(torch.isnan(v.camera_center).all() for v in observations(no_camera, 40, packed))
    with pytest.raises(StrategyError, match=r"info\['camtoworlds'\]") as err:
        observations(no_camera, 40, packed, need_camera=True)
    assert "\n" not in str(err.value)
    with pytest.raises(StrategyError, match=r"\[\.\.\., C, 4, 4\]"):
        camera_centers({"viewmats": torch.eye(3)})


def test_from_default_keeps_gsplat_settings_and_fields_are_checked():
    splatfacto_like = GsDefault(prune_opa=0.1, refine_every=50, pause_refine_after_reset=130, absgrad=True)
    s = integ.GsplatSeedSplitStrategy.from_default(splatfacto_like, seed=4, splitting=RandomSplitting(n_split=7))
    assert isinstance(s, GsDefault)
    assert (s.prune_opa, s.refine_every, s.pause_refine_after_reset, s.absgrad) == (0.1, 50, 130, True)
    resolved = dict(s.resolved_operators())
    assert (s.seed, resolved["splitting"].n_split, resolved["splitting"].every) == (4, 7, 1)
    assert (resolved["seeding"].n_seed, resolved["seeding"].every, resolved["seeding"].prune_scale3d) == (20, 50, 10.0)
    with pytest.raises(StrategyError, match="needs a gsplat DefaultStrategy, got MCMCStrategy"):
        integ.GsplatSeedStrategy.from_default(GsMCMC())
    # the operators check their own fields, as in eg-train
    with pytest.raises(StrategyError, match="RandomSeeding.n_seed must be >= 0"):
        integ.GsplatSeedSplitStrategy(seeding=RandomSeeding(n_seed=-1))
    with pytest.raises(StrategyError, match="RandomSplitting.every must be >= 1"):
        integ.GsplatSeedSplitStrategy(splitting=RandomSplitting(every=0))
    with pytest.raises(StrategyError, match="unknown exploration budget"):
        integ.GsplatSeedSplitStrategy(budget="huge")


def test_outside_the_refine_window_only_gsplat_runs():
    strategy = integ.GsplatSeedSplitStrategy(**SCHEDULE)
    params, optimizers = make_params("gsplat", n=40)
    state = strategy.initialize_state()
    info, _, loss = fake_render(params, 7, "pairs", False)
    strategy.step_pre_backward(params, optimizers, state, 7, info)
    loss.backward()
    assert strategy.step_post_backward(params, optimizers, state, 7, info) == {
        "random_split": 0, "seeded": 0, "seeds_pruned": 0}
    assert params["means"].shape[0] == 40 and state["grad2d"] is None  # gsplat's step returned at once


def test_imports_without_gsplat_and_the_old_module_are_one_clear_line(monkeypatch):
    monkeypatch.setitem(sys.modules, "gsplat", None)
    monkeypatch.delitem(sys.modules, "exploregs_plugin.integrations.into_gsplat")
    with pytest.raises(ImportError, match=r"pip install gsplat==1\.5\.3") as err:
        importlib.import_module("exploregs_plugin.integrations.into_gsplat")
    assert "\n" not in str(err.value)
    monkeypatch.undo()
    with pytest.raises(ImportError, match=r"is now exploregs_plugin\.integrations\.into_gsplat: SeedSplitStrategy -> "
                                          r"GsplatSeedSplitStrategy.*n_split -> splitting\.n_split") as err:
        importlib.import_module("exploregs_plugin.integrations.gsplat")
    assert "\n" not in str(err.value)


# ------------------------------------------------------------------------------ the same operators as eg-train
PAIRS = [(integ.GsplatSplitStrategy, SplittingStrategy), (integ.GsplatSeedStrategy, SeedingStrategy),
         (integ.GsplatSeedSplitStrategy, SeedSplitStrategy), (integ.GsplatRayStrategy, RayPerturbationStrategy)]


def _operator_fields(cls) -> list[tuple[str, type, object]]:
    return [(f.name, f.type, f.default_factory()) for f in dataclasses.fields(cls)
            if f.default_factory is not dataclasses.MISSING and isinstance(f.default_factory(), Operator)]


@pytest.mark.parametrize("adapter, ours", PAIRS)
@pytest.mark.parametrize("budget", ["paper", "cpu-small"])
def test_each_adapter_holds_eg_trains_operators_and_budget(adapter, ours, budget):
    # the same operator fields (names, config classes, defaults) in the same order, so the same
    # options in both trainers (--strategy.seeding.n-seed), and the same values from the budget
    assert _operator_fields(adapter) == _operator_fields(ours) != []
    window = dict(refine_start_iter=500, refine_stop_iter=15_000, refine_every=100, reset_every=3000)
    schedule = Schedule(max_steps=30_000, refine_start=500, refine_stop=15_000, refine_every=100, reset_every=3000,
                        sh_degree_interval=1000, views_per_step=CAMERAS)
    resolved = ours(budget=budget).setup(schedule).operators()
    assert adapter(**window, budget=budget).resolved_operators(CAMERAS) == resolved
    assert isinstance(adapter(), GsDefault)


def _our_rows(params, optimizers) -> dict[str, list[Tensor]]:
    """Every parameter with its two Adam moments, under our names and row shapes."""
    out = {}
    for name, p in params.items():
        ours, n = integ.OUR_NAMES.get(name, name), p.shape[0]
        shape = {"opacities": (n,), "sh0": (n, 1, 3)}.get(ours, tuple(p.shape))
        out[ours] = [t.detach().reshape(shape) for t in (p, *_moments(optimizers, params, name))]
    return out


LOCKSTEP = dict(refine_start_iter=1, refine_stop_iter=9, refine_every=3, reset_every=1000, grow_grad2d=2e-4,
                grow_scale3d=1e9)
"""Refinements at 3 and 6, Random Splitting on steps 2-8, no opacity reset (gsplat 1.5.3 never
resets, our Default would), and 3DGS growth by clones only: gsplat's own split draws from the
global generator through a rotation that rounds differently from ours (from_gsplat's tests)."""
LR = 1e-3  # make_params' Adam learning rate: what the adapters read when no lr is passed


def lockstep(theirs, ours, layout: str = "gsplat", steps=range(10)) -> collections.Counter:
    """``theirs`` through gsplat's API (fake renders, ``info``) and ``ours`` through eg-train's
    (``step_post_backward`` with our observations and a generator seeded as theirs is), from the
    same Gaussians; after every step the same counts, parameters, moments and statistics.
    Returns eg-train's counts summed over the steps."""
    mcmc = isinstance(theirs, GsMCMC)
    their_params, their_opt = make_params(layout)
    our_params, our_opt = make_params("gsplat")
    their_state = theirs.initialize_state(scene_scale=1.0)
    our_state = ours.initialize_state(scene_scale=1.0)
    theirs.check_sanity(their_params, their_opt)
    ours.check_sanity(our_params, our_opt)
    generator = torch.Generator().manual_seed(theirs.seed)
    totals: collections.Counter = collections.Counter()
    for step in steps:
        info, _, loss = fake_render(their_params, step, "pairs", False)
        theirs.step_pre_backward(their_params, their_opt, their_state, step, info)
        loss.backward()
        adam_step(their_opt)
        our_info, _, our_loss = fake_render(our_params, step, "pairs", False)
        our_info["means2d"].retain_grad()
        our_loss.backward()
        adam_step(our_opt)
        views = [ViewObservation(W, H, our_info["radii"][c], center, means2d_grad=our_info["means2d"].grad[c],
                                 n_cameras=CAMERAS) for c, center in enumerate(native_centers())]
        their_counts = theirs.step_post_backward(their_params, their_opt, their_state, step, info,
                                                 **({"lr": LR} if mcmc else {}))
        our_counts = ours.step_post_backward(our_params, our_opt, our_state, step, views, lr=LR, generator=generator)
        assert {key: our_counts[key] for key in their_counts} == their_counts, step
        theirs_rows, our_rows = _our_rows(their_params, their_opt), _our_rows(our_params, our_opt)
        assert theirs_rows.keys() == our_rows.keys()
        for name, tensors in our_rows.items():
            assert all(torch.equal(a, b) for a, b in zip(theirs_rows[name], tensors)), (step, name)
        their_stats = their_state["stats"] if mcmc else their_state
        for key, value in our_state["stats"].items():
            assert torch.equal(their_stats[key], value), (step, key)
        totals.update(our_counts)
    assert torch.equal(their_state["generator"].get_state(), generator.get_state())
    return totals


def _schedule(**overrides) -> Schedule:
    fields = dict(max_steps=10, refine_start=1, refine_stop=9, refine_every=3, reset_every=1000,
                  sh_degree_interval=1000, views_per_step=CAMERAS)
    return Schedule(**{**fields, **overrides})


@pytest.mark.parametrize("layout", ["gsplat", "nerfstudio"])
@pytest.mark.parametrize("budget", ["paper", "cpu-tiny"])
def test_seed_split_adds_splits_and_prunes_the_rows_eg_train_does(layout, budget):
    # probation at 0.5: the seeds of step 3 below it (and their split children) go at step 6
    seeding = RandomSeeding(prune_opa=0.5)
    theirs = integ.GsplatSeedSplitStrategy(**LOCKSTEP, budget=budget, seeding=seeding, seed=3)
    ours = SeedSplitStrategy(**LOCKSTEP, budget=budget, seeding=seeding).setup(_schedule())
    totals = lockstep(theirs, ours, layout)
    assert min(totals["random_split"], totals["seeded"], totals["cloned"]) > 0, totals
    assert totals["pruned"] > totals["seeds_pruned"]  # gsplat's opacity prune and the probation, one set
    if budget == "paper":  # 20 seeds at step 3 (cpu-tiny: 2, all above 0.5 here)
        assert totals["seeds_pruned"] > 0, totals


def test_verbose_prints_one_line_per_refinement_with_the_counts_since_the_last(capsys):
    # the paper budget splits at every step: one line per step would drown gsplat's own lines
    theirs = integ.GsplatSeedSplitStrategy(**LOCKSTEP, seed=3, verbose=True)
    ours = SeedSplitStrategy(**LOCKSTEP).setup(_schedule())
    totals = lockstep(theirs, ours, steps=range(10))
    lines = [ln for ln in capsys.readouterr().out.splitlines() if "(since the last line)" in ln]
    steps = [int(ln.split(":")[0].split()[1]) for ln in lines]
    assert steps == [3, 6, 9], lines  # refine_every 3; step 0 changed nothing
    printed = collections.Counter()
    for line in lines:
        for part in line.split(": ", 1)[1].split(" (since")[0].split(", "):
            key, value = part.rsplit(" ", 1)
            printed[key] += int(value)
    # every count of steps 0-9 appears once, in the line of the refinement that followed it
    assert printed["random_split"] == totals["random_split"] > 0
    assert printed["seeded"] == totals["seeded"] > 0
    assert "perturbed" not in printed


@pytest.mark.parametrize("adapter, ours", PAIRS[:2])
def test_seeding_alone_and_splitting_alone_are_eg_trains(adapter, ours):
    totals = lockstep(adapter(**LOCKSTEP, seed=8), ours(**LOCKSTEP).setup(_schedule()))
    assert totals["random_split"] + totals["seeded"] > 0 and totals["cloned"] > 0


@pytest.mark.parametrize("layout", ["gsplat", "nerfstudio"])
def test_ray_noise_and_densification_are_eg_trains(layout):
    # the noise on every step, through the refinements and after the window (step 9)
    totals = lockstep(integ.GsplatRayStrategy(**LOCKSTEP, seed=2), RayPerturbationStrategy(**LOCKSTEP), layout)
    assert totals["perturbed"] > 0 and totals["cloned"] > 0


def test_mcmc_ray_is_eg_trains_mcmc_with_ray_noise():
    window = dict(refine_start_iter=1, refine_stop_iter=9, refine_every=3)
    theirs = integ.GsplatMCMCRayStrategy(**window, cap_max=340, seed=5)
    ours = MCMCStrategy(**window, reset_every=3, cap_max=340, noise=PositionNoise(mode="ray"))
    assert integ.GsplatMCMCRayStrategy().noise == PositionNoise(mode="ray")  # eg-train's --strategy.noise.mode ray
    totals = lockstep(theirs, ours, "nerfstudio")
    assert totals["relocated"] > 0 and totals["perturbed"] > 0
    assert totals["added"] == 30  # 300 -> 315 -> 330 at steps 3 and 6


# ------------------------------------------------------------------------------ ray perturbation
NO_REFINE = dict(refine_start_iter=100, refine_stop_iter=200, refine_every=50)  # no refine at NOISE_STEPS
NOISE_STEPS = (0, 1, 2, 250)  # 250: after the refine window, where the noise goes on


def with_camera(info, camera: str):
    """``info`` with the first camera under ``camera`` (one of CAMERA_KEYS) instead of viewmats."""
    info = {k: v for k, v in info.items() if k != "viewmats"}
    if camera == "viewmats":
        info["viewmats"] = VIEWMATS
    elif camera == "camtoworlds":
        c2w = torch.linalg.inv(VIEWMATS)
        c2w[0, :3, 3] = native_centers()[0]  # exactly the native centre, so the noise can agree bit for bit
        info["camtoworlds"] = c2w
    else:
        info["camera_center"] = native_centers()[0]
    return info


def off_ray(displacement: Tensor, means: Tensor, center: Tensor) -> Tensor:
    """|d x r| / |r| per row in float64: the component of the displacement d off the ray r from
    the camera centre to the Gaussian's position before the noise."""
    ray = means.double() - center.double()
    return torch.linalg.cross(displacement.double(), ray).norm(dim=-1) / ray.norm(dim=-1)


def assert_only_along_rays(before: Tensor, after: Tensor) -> None:
    """Some means moved, and every displacement is along its ray up to float32 rounding of the
    new position (|d x r| / |r| <= 1e-6 (1 + |mean|))."""
    d = after.double() - before.double()
    assert (d.norm(dim=-1) > 0).any()
    bound = 1e-6 * (1.0 + after.double().norm(dim=-1))
    assert (off_ray(d, before, native_centers()[0]) <= bound).all()


def native_and_gsplat(kind: str):
    """Our native strategy and its gsplat counterpart, neither refining at NOISE_STEPS."""
    if kind == "ray":
        native = RayPerturbationStrategy(grow_grad2d=1e9, prune_opa=0.0, reset_every=1000, **NO_REFINE)
        return native, integ.GsplatRayStrategy(**NO_REFINE, reset_every=1000, seed=7)
    native = MCMCStrategy(noise=PositionNoise(mode="ray"), cap_max=10_000, reset_every=1000, **NO_REFINE)
    return native, integ.GsplatMCMCRayStrategy(**NO_REFINE, seed=7)


NOISE_CASES = [("gsplat", "pairs", False, "viewmats"), ("gsplat", "single", True, "camtoworlds"),
               ("nerfstudio", "pairs", True, "camera_center"), ("nerfstudio", "single", False, "viewmats")]


@pytest.mark.parametrize("kind", ["ray", "mcmc-ray"])
@pytest.mark.parametrize("layout,radii,packed,camera", NOISE_CASES)
def test_ray_noise_through_gsplat_moves_means_bit_for_bit_as_our_native_strategy(kind, layout, radii, packed, camera):
    native, strategy = native_and_gsplat(kind)
    params, optimizers = make_params(layout)
    ref_params, ref_optimizers = make_params("gsplat")  # the same values in our layout
    n = ref_params["means"].shape[0]
    state = strategy.initialize_state()
    ref_state = native.initialize_state()
    generator = torch.Generator().manual_seed(7)  # what the gsplat strategy makes from seed=7
    for step in NOISE_STEPS:
        info, _, loss = fake_render(params, step, radii, packed)
        info = with_camera(info, camera)
        strategy.step_pre_backward(params, optimizers, state, step, info)
        loss.backward()
        before = params["means"].detach().clone()
        extra = {"packed": packed} if kind == "ray" else {"lr": LR}  # each class's gsplat signature
        counts = strategy.step_post_backward(params, optimizers, state, step, info, **extra)
        views = synthetic_views(torch.zeros(n, 2), torch.ones(n, dtype=torch.bool), W, H, native_centers()[0])
        ref_counts = native.step_post_backward(ref_params, ref_optimizers, ref_state, step, views, lr=LR,
                                               generator=generator)
        assert counts["perturbed"] == ref_counts["perturbed"] == n
        assert torch.equal(params["means"], ref_params["means"])
        assert_only_along_rays(before, params["means"].detach())
        for p in params.values():
            p.grad = None
    assert params["opacities"].shape[1:] == ((1,) if layout == "nerfstudio" else ())


def assert_ray_rows(step, n_before, reference, after, counts):
    """gsplat's densification exactly (every other parameter, every moment, gsplat's statistics),
    and the means moved only along their rays."""
    ref_params, ref_opts, ref_state = reference
    params, optimizers, state = after
    assert counts["perturbed"] == params["means"].shape[0] == ref_params["means"].shape[0]
    for key in params:
        if key != "means":
            assert torch.equal(params[key], ref_params[key]), key
        for mine, ref in zip(_moments(optimizers, params, key), _moments(ref_opts, ref_params, key)):
            assert torch.equal(mine, ref), key
    for key, value in ref_state.items():
        if isinstance(value, Tensor):
            assert torch.equal(state[key], value), key
    assert_only_along_rays(ref_params["means"].detach(), params["means"].detach())


@pytest.mark.parametrize("layout,radii,packed", [("gsplat", "pairs", False), ("gsplat", "single", True),
                                                 ("nerfstudio", "pairs", True)])
def test_ray_strategy_keeps_gsplat_densification_and_moments_aligned(layout, radii, packed):
    strategy = integ.GsplatRayStrategy(**SCHEDULE, seed=2)
    sizes = []

    def check(step, n_before, reference, after, counts):
        assert_ray_rows(step, n_before, reference, after, counts)
        sizes.append(after[0]["means"].shape[0])

    train(strategy, layout, radii, packed, check=check)
    assert len(set(sizes)) > 1  # gsplat's refine changed the set, and the rows stayed aligned


def relocation_on_cpu(opacities, scales, ratios, binoms):
    """gsplat's compute_relocation (a CUDA kernel) for the reference run on the CPU: eq. 9 by
    our relocation_update, in the shapes gsplat's kernel returns."""
    new_o, new_s = relocation_update(opacities.reshape(-1), scales, ratios.clamp(1, binoms.shape[0]), binoms.double())
    return new_o.reshape(opacities.shape), new_s


def _snapshot(params, optimizers):
    return ({k: p.detach().clone() for k, p in params.items()},
            {k: [m.clone() for m in _moments(optimizers, params, k)] for k in params})


@pytest.mark.parametrize("layout", ["gsplat", "nerfstudio"])
def test_mcmc_ray_relocates_and_grows_by_gsplats_rules_with_moments_following_rows(layout, monkeypatch):
    gsplat_relocate = GsMCMC._relocate_gs
    monkeypatch.setattr(gsplat.strategy.ops, "compute_relocation", relocation_on_cpu)  # the reference's kernel
    monkeypatch.setattr(GsMCMC, "_relocate_gs", lambda *a: pytest.fail("gsplat's relocation runs: ours should"))
    settings = dict(refine_start_iter=0, refine_every=2, refine_stop_iter=100, cap_max=310)
    # no noise: rows stay recognisable
    strategy = integ.GsplatMCMCRayStrategy(**settings, noise=PositionNoise(mode="ray", lr=0.0), seed=1)
    params, optimizers = make_params(layout)
    info, _, loss = fake_render(params, 0, "pairs", False)
    loss.backward()
    adam_step(optimizers)  # non-zero moments everywhere
    state = strategy.initialize_state()
    for step in (1, 2, 4):  # 1: noise only; 2, 4: relocation and growth (capped at 310 on step 2)
        ref_params, ref_opts = copy.deepcopy((params, optimizers))
        plain = GsMCMC(**settings)
        torch.manual_seed(step)
        ref_relocated = ref_added = 0
        if step % 2 == 0:
            binoms = plain.initialize_state()["binoms"]
            ref_relocated = gsplat_relocate(plain, ref_params, ref_opts, binoms)
            ref_added = plain._add_new_gs(ref_params, ref_opts, binoms)
        (before, moments), n_old = _snapshot(params, optimizers), params["means"].shape[0]
        dead = torch.sigmoid(before["opacities"].reshape(-1)) <= strategy.min_opacity
        counts = strategy.step_post_backward(params, optimizers, state, step, info, lr=LR)
        assert (counts["relocated"], counts["added"]) == (ref_relocated, ref_added)
        n = params["means"].shape[0]
        assert n == ref_params["means"].shape[0] <= strategy.cap_max
        assert n == (310 if step > 1 else 300)
        unchanged = torch.ones(n_old, dtype=torch.bool)
        for key in params:
            assert params[key].shape[1:] == before[key].shape[1:] and optimizers[key].param_groups[0]["params"][0] is params[key]
            unchanged &= (params[key].detach()[:n_old] == before[key]).reshape(n_old, -1).all(-1)
        if step % 2 == 0:
            assert counts["relocated"] == int(dead.sum()) and (step != 2 or counts["relocated"] > 0)
            assert not (unchanged & dead).any()  # every dead row took a live source's place
        else:
            assert unchanged.all()
        for key in params:
            now = _moments(optimizers, params, key)
            for m, m_before in zip(now, moments[key]):
                assert torch.equal(m[:n_old][unchanged], m_before[unchanged]), key  # kept rows keep theirs
                assert step % 2 or not m[:n_old][dead].any(), key  # relocated rows start again
                assert not m[n_old:].any(), key  # so do new rows
        info, _, _ = fake_render(params, step, "pairs", False)  # the next step's render of the new set
    assert state["generator"] is not None


def test_missing_camera_zero_lr_and_bad_noise_fields_are_one_line():
    params, optimizers = make_params("gsplat", n=20)
    info, _, _ = fake_render(params, 0, "pairs", False)
    no_camera = {k: v for k, v in info.items() if k != "viewmats"}
    strategy = integ.GsplatMCMCRayStrategy(**NO_REFINE)
    state = strategy.initialize_state()
    with pytest.raises(StrategyError, match="camtoworlds"):
        strategy.step_post_backward(params, optimizers, state, 0, no_camera, lr=LR)
    with pytest.raises(StrategyError, match="lr="):
        strategy.step_post_backward(params, optimizers, state, 0, info, lr=0.0)
    ray = integ.GsplatRayStrategy(**NO_REFINE)
    with pytest.raises(StrategyError, match="camtoworlds"):
        ray.step_post_backward(params, optimizers, ray.initialize_state(), 0, no_camera)
    with pytest.raises(StrategyError, match=r"set noise\.lr \(--strategy\.noise\.lr\) instead of gsplat's noise_lr"):
        integ.GsplatMCMCRayStrategy(noise_lr=1e3)
    with pytest.raises(StrategyError, match="'isotropic' or 'ray'"):
        integ.GsplatRayStrategy(noise=PositionNoise(mode="cone"))


# ------------------------------------------------------------------------------ a training loop
def _scene(seed: int, n: int):
    """Gaussians in gsplat's layout (sh degree 1) in the box [-1, 1]^3, and four cameras at
    distance 3 around it (our rasterizer's OpenCV viewmats, 32 x 32 pixels)."""
    from exploregs_plugin.strategies.synthetic import make_gaussians

    params = make_gaussians(n, torch.Generator().manual_seed(seed), sh_degree=1, extent=0.8)
    with torch.no_grad():
        params["scales"].add_(1.5)  # 0.02 -> 0.09 x extent: a few pixels wide
    K = torch.tensor([[40.0, 0.0, 16.0], [0.0, 40.0, 16.0], [0.0, 0.0, 1.0]])
    cams = [viewmat((3.0 * math.sin(a), 0.0, -3.0 * math.cos(a)), a) for a in (0.0, 0.5, -0.5, 1.0)]  # facing the origin
    return params, cams, K


def render(params, view, K):
    """Our rasterizer (pure-torch backend), and gsplat's info for one camera as rasterization()
    gives it to simple_trainer: means2d [C, N, 2], radii [C, N, 2], width, height, n_cameras,
    gaussian_ids (None: unpacked), plus the viewmats that our simple_trainer wrapper adds.

    Our renderer differentiates 2D means [N, 2]; gsplat's strategies read the gradient of a
    [C, N, 2] tensor, so ``info["means2d"]`` is a leaf of that shape whose gradient
    :func:`gradient_to_info` fills from ours after ``loss.backward()``."""
    from exploregs_plugin.rasterizer import RasterSettings, rasterize

    sh = torch.cat([params["sh0"], params["shN"]], dim=1)
    image, _, _, ours = rasterize(params["means"], params["quats"], torch.exp(params["scales"]),
                                  torch.sigmoid(params["opacities"]), sh, Camera(view, K, 32, 32),
                                  settings=RasterSettings(backend="torch"))
    if ours["means2d"].requires_grad:
        ours["means2d"].retain_grad()
    info = {"means2d": ours["means2d"].detach()[None].requires_grad_(), "radii": ours["radii"][None], "width": 32,
            "height": 32, "n_cameras": 1, "gaussian_ids": None, "viewmats": view[None], "ours": ours["means2d"]}
    return image, info


def gradient_to_info(info) -> None:
    info["means2d"].grad = info.pop("ours").grad[None]


@pytest.mark.parametrize("kind", ["seedsplit", "ray", "mcmc-ray"])
def test_a_short_training_loop_with_our_renderer_improves_psnr(kind):
    from exploregs_plugin.model.losses import psnr

    truth, cams, K = _scene(0, 120)
    with torch.no_grad():
        targets = [render(truth, view, K)[0] for view in cams]
    params, _, _ = _scene(1, 60)
    optimizers = {k: torch.optim.Adam([{"params": p, "lr": lr, "name": k}], eps=1e-15)
                  for (k, p), lr in zip(params.items(), (1.6e-3, 5e-3, 1e-3, 5e-2, 2.5e-3, 1e-4))}
    window = dict(refine_start_iter=4, refine_stop_iter=24, refine_every=8)
    if kind == "mcmc-ray":
        strategy = integ.GsplatMCMCRayStrategy(**window, cap_max=90, seed=0)
        state = strategy.initialize_state()
    else:
        cls = integ.GsplatSeedSplitStrategy if kind == "seedsplit" else integ.GsplatRayStrategy
        extra = ({"seeding": RandomSeeding(n_seed=5), "splitting": RandomSplitting(n_split=2, every=4)}
                 if kind == "seedsplit" else {})
        strategy = cls(**window, reset_every=1000, grow_grad2d=1e-4, **extra, seed=0)
        state = strategy.initialize_state(scene_scale=1.0)
    strategy.check_sanity(params, optimizers)

    def mean_psnr():
        with torch.no_grad():
            return sum(psnr(render(params, v, K)[0], t) for v, t in zip(cams, targets)) / len(cams)

    start, counts = mean_psnr(), []
    for step in range(32):
        view = step % len(cams)
        image, info = render(params, cams[view], K)
        strategy.step_pre_backward(params, optimizers, state, step, info)
        loss = (image - targets[view]).abs().mean()
        loss.backward()
        gradient_to_info(info)
        for opt in optimizers.values():
            opt.step()
            opt.zero_grad(set_to_none=True)
        if kind == "mcmc-ray":  # simple_trainer's two calls
            counts.append(strategy.step_post_backward(params, optimizers, state, step, info, lr=1.6e-3))
        else:
            counts.append(strategy.step_post_backward(params, optimizers, state, step, info, packed=False))
    end = mean_psnr()
    assert end > start + 1.0, (start, end)
    assert params["means"].shape[0] != 60  # the set changed on the way (rows and moments stayed aligned)
    if kind == "seedsplit":
        assert sum(c.get("random_split", 0) + c.get("seeded", 0) for c in counts) > 0
    else:  # the noise ran on every step, with the set's size at that step
        assert all(c["perturbed"] > 0 for c in counts) and counts[-1]["perturbed"] == params["means"].shape[0]
    if kind == "mcmc-ray":
        assert sum(c["added"] for c in counts) == params["means"].shape[0] - 60 > 0


# ------------------------------------------------------------------------------ simple_trainer wrapper
STAND_IN_TRAINER = """
# simple_trainer.py's structure where the wrapper reaches in: gsplat's rasterization imported by
# name, a Config whose strategy is Union[DefaultStrategy, MCMCStrategy], its configs dict
# handed to tyro.extras.overridable_config_cli in __main__.
from dataclasses import dataclass, field
from typing import Union

import torch
import tyro
from gsplat.rendering import rasterization
from gsplat.strategy import DefaultStrategy, MCMCStrategy


@dataclass
class Config:
    init_opa: float = 0.1
    opacity_reg: float = 0.0
    strategy: Union[DefaultStrategy, MCMCStrategy] = field(default_factory=DefaultStrategy)


if __name__ == "__main__":
    configs = {
        "default": ("3DGS.", Config(strategy=DefaultStrategy(verbose=True))),
        "mcmc": ("MCMC.", Config(init_opa=0.5, opacity_reg=0.01, strategy=MCMCStrategy(verbose=True))),
    }
    cfg = tyro.extras.overridable_config_cli(configs)
    _, _, info = rasterization(None, None, None, None, None, torch.eye(4)[None], None, 8, 8)
"""


def test_simple_trainer_wrapper_adds_our_configs_and_the_camera(tmp_path, monkeypatch):
    import gsplat.rendering

    from exploregs_plugin.integrations import simple_trainer as wrapper

    def fake_rasterization(means, quats, scales, opacities, colors, viewmats, Ks, width, height, **kwargs):
        return None, None, {"width": width}  # gsplat's own info has no camera

    monkeypatch.setattr(gsplat.rendering, "rasterization", fake_rasterization)
    (tmp_path / "examples").mkdir()
    script = tmp_path / "examples" / "simple_trainer.py"
    script.write_text(STAND_IN_TRAINER, "utf8")
    run = wrapper.run([str(script), "mcmc-ray", "--strategy.noise.lr", "1000", "--strategy.seed", "4"])
    cfg, info = run["cfg"], run["info"]
    assert isinstance(cfg.strategy, integ.GsplatMCMCRayStrategy) and isinstance(cfg.strategy, GsMCMC)
    assert (cfg.strategy.noise, cfg.strategy.seed, cfg.strategy.verbose) == (PositionNoise("ray", 1000.0), 4, True)
    assert (cfg.init_opa, cfg.opacity_reg) == (0.5, 0.01)  # simple_trainer's own mcmc settings
    assert torch.equal(info["viewmats"], torch.eye(4)[None]) and info["width"] == 8
    assert gsplat.rendering.rasterization is fake_rasterization  # put back after the run
    cfg = wrapper.run([str(script), "seedsplit", "--strategy.splitting.n-split", "5", "--strategy.seeding.prune-opa",
                       "0.1"])["cfg"]
    strategy = cfg.strategy
    assert isinstance(strategy, integ.GsplatSeedSplitStrategy) and cfg.init_opa == 0.1
    assert (strategy.splitting.n_split, strategy.seeding.prune_opa, strategy.seeding.n_seed) == (5, 0.1, None)
    assert isinstance(wrapper.run([str(script), "default"])["cfg"].strategy, GsDefault)
    with pytest.raises(SystemExit, match="usage"):
        wrapper.run(["seedsplit"])
