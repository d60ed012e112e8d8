"""Ray perturbation and 3DGS-MCMC: noise geometry, relocation formula, growth, gsplat agreement."""

from __future__ import annotations

import copy
import math

import pytest
import torch

from exploregs_plugin.schedule import ScheduleConfig
from exploregs_plugin.strategies import MCMCStrategy, PositionNoise, RayPerturbationStrategy, StrategyError
from exploregs_plugin.rasterizer.projection import covariances_3d
from exploregs_plugin.strategies.position_noise import position_noise
from exploregs_plugin.strategies.relocation import binomial_table, relocation_update
from exploregs_plugin.strategies.synthetic import adam_steps, make_gaussians, make_optimizers, synthetic_views

WINDOW = dict(refine_start_iter=2, refine_stop_iter=500, refine_every=10, reset_every=100)


def _info(n, camera_center=None):
    return synthetic_views(torch.zeros(n, 2), torch.ones(n, dtype=torch.bool), 32, 32, camera_center)


# ------------------------------------------------------------------------------ noise
def test_ray_noise_is_parallel_to_the_camera_ray_float64():
    g = torch.Generator().manual_seed(0)
    params = make_gaussians(200, g, dtype=torch.float64)
    cam = torch.tensor([0.3, -2.0, 4.0], dtype=torch.float64)
    with torch.no_grad():
        params["opacities"].fill_(-6.0)  # transparent: the gate is open
    eta = position_noise(params["means"], params["quats"], params["scales"], params["opacities"], 5e5 * 1.6e-4,
                         torch.Generator().manual_seed(1), mode="ray", camera_center=cam)
    assert eta.dtype == torch.float64
    ray = params["means"].detach() - cam
    cos = (eta * ray).sum(-1) / (eta.norm(dim=-1) * ray.norm(dim=-1))
    assert torch.all(eta.norm(dim=-1) > 0)
    assert torch.all(cos.abs() > 1 - 1e-9)


def test_noise_is_gated_by_opacity_and_shaped_by_covariance():
    g = torch.Generator().manual_seed(2)
    params = make_gaussians(6, g, dtype=torch.float64)
    with torch.no_grad():
        params["opacities"].copy_(torch.logit(torch.tensor([0.99, 0.9, 0.5, 0.005, 0.001, 1e-4], dtype=torch.float64)))
    scale = 5e5 * 1e-4
    eta = position_noise(params["means"], params["quats"], params["scales"], params["opacities"], scale,
                         torch.Generator().manual_seed(3))
    z = torch.randn(6, 3, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    o = torch.sigmoid(params["opacities"].detach())
    gate = torch.sigmoid(-100.0 * (o - 0.005))
    sigma = covariances_3d(params["quats"].detach(), torch.exp(params["scales"].detach()))
    expected = torch.einsum("nij,nj->ni", sigma, z) * (gate * scale)[:, None]
    assert torch.allclose(eta, expected, rtol=1e-12, atol=0)
    assert eta[:2].norm(dim=-1).max() < 1e-30  # opaque: essentially frozen
    assert torch.isclose(gate[3], torch.tensor(0.5, dtype=torch.float64))
    assert eta[5].norm() > 0


def test_ray_strategy_moves_means_only_along_rays_after_each_step():
    g = torch.Generator().manual_seed(4)
    params = make_gaussians(50, g)
    with torch.no_grad():
        params["opacities"].fill_(-5.0)
    optimizers = make_optimizers(params)
    s = RayPerturbationStrategy(grow_grad2d=1e9, prune_opa=0.0, **WINDOW)
    state = s.initialize_state()
    cam = torch.tensor([0.0, 0.0, -3.0])
    before = params["means"].detach().clone()
    counts = s.step_post_backward(params, optimizers, state, 3, _info(50, cam), lr=1.6e-4, generator=torch.Generator().manual_seed(0))
    assert counts["perturbed"] == 50
    moved = params["means"].detach() - before
    ray = before - cam
    cross = torch.linalg.cross(moved.double(), ray.double()).norm(dim=-1) / ray.double().norm(dim=-1)
    # float32 means: the component off the ray is only rounding (~eps x |mean|), while the
    # movement along the ray is orders of magnitude larger.
    assert float(moved.norm(dim=-1).median()) > 1e-3
    assert float(cross.max()) < 1e-6
    # Noise continues after densification stops (it is applied after every optimizer step).
    before = params["means"].detach().clone()
    s.step_post_backward(params, optimizers, state, 900, _info(50, cam), lr=1.6e-4, generator=torch.Generator().manual_seed(1))
    assert not torch.equal(before, params["means"].detach())
    with pytest.raises(StrategyError, match="lr="):
        s.step_post_backward(params, optimizers, state, 901, _info(50, cam), generator=torch.Generator())
    info = _info(50)
    info[0].camera_center = None  # a view without its camera (the guard of ray noise)
    with pytest.raises(StrategyError, match="camera_center"):
        s.step_post_backward(params, optimizers, state, 902, info, lr=1e-4, generator=torch.Generator())


# ------------------------------------------------------------------------------ relocation
def _direct_relocation(o: float, s: float, n: int) -> tuple[float, float]:
    """The paper's eq. 9 evaluated literally, in Python floats."""
    new_o = 1.0 - (1.0 - o) ** (1.0 / n)
    denom = 0.0
    for i in range(1, n + 1):
        for k in range(i):
            denom += math.comb(i - 1, k) * (-1) ** k * new_o ** (k + 1) / math.sqrt(k + 1)
    return new_o, o * s / denom


@pytest.mark.parametrize("n", [1, 2, 3, 5, 10, 25, 51])
def test_relocation_matches_direct_formula(n):
    ops_ = torch.tensor([0.005, 0.05, 0.3, 0.7, 0.95, 0.999], dtype=torch.float64)
    scales = torch.tensor([[0.1, 0.2, 0.05]], dtype=torch.float64).repeat(len(ops_), 1)
    new_o, new_s = relocation_update(ops_, scales, torch.full((len(ops_),), n), binomial_table())
    for i, o in enumerate(ops_.tolist()):
        want_o, want_s = _direct_relocation(o, 0.1, n)
        assert math.isclose(float(new_o[i]), want_o, rel_tol=1e-12)
        assert math.isclose(float(new_s[i, 0]), want_s, rel_tol=1e-6)
        assert math.isclose(float(new_s[i, 1]) / float(new_s[i, 0]), 2.0, rel_tol=1e-12)
        # n copies blended at the centre give back the original opacity.
        assert math.isclose(1.0 - (1.0 - float(new_o[i])) ** n, o, rel_tol=1e-9)
    if n == 1:
        assert torch.allclose(new_s, scales) and torch.allclose(new_o, ops_)


@pytest.mark.parametrize("n", [2, 3])
def test_relocated_pair_preserves_opacity_profile_integral(n):
    """The scale update keeps the 1D integral of the blended opacity profile (the paper's aim)."""
    o, s = 0.6, 0.3
    new_o, new_s = relocation_update(torch.tensor([o], dtype=torch.float64), torch.full((1, 3), s, dtype=torch.float64),
                                     torch.tensor([n]), binomial_table())
    x = torch.linspace(-10, 10, 200_001, dtype=torch.float64)
    single = o * torch.exp(-0.5 * (x / s) ** 2)
    blended = 1 - (1 - float(new_o) * torch.exp(-0.5 * (x / float(new_s[0, 0])) ** 2)) ** n
    assert math.isclose(float(torch.trapezoid(blended, x)), float(torch.trapezoid(single, x)), rel_tol=1e-6)
    assert math.isclose(float(blended[100_000]), o, rel_tol=1e-12)  # same opacity at the centre


# ------------------------------------------------------------------------------ MCMC strategy
def test_mcmc_reuses_dead_and_never_exceeds_cap():
    g = torch.Generator().manual_seed(5)
    params = make_gaussians(100, g)
    optimizers = make_optimizers(params)
    adam_steps(params, optimizers, g)
    with torch.no_grad():
        params["opacities"][:30] = -8.0
    s = MCMCStrategy(cap_max=130, **WINDOW)
    state = s.initialize_state()
    gen = torch.Generator().manual_seed(0)
    counts = s.step_post_backward(params, optimizers, state, 10, _info(100), lr=1e-4, generator=gen)
    assert counts["relocated"] == 30 and counts["added"] == 5
    assert params["means"].shape[0] == 105
    assert torch.all(torch.sigmoid(params["opacities"].detach()[:30]) > 0.005)  # reused rows, alive
    sizes = []
    for step in range(11, 200):
        n = params["means"].shape[0]
        s.step_post_backward(params, optimizers, state, step, _info(n), lr=1e-4, generator=gen)
        sizes.append(params["means"].shape[0])
        for name, p in params.items():
            assert optimizers[name].state[p]["exp_avg"].shape == p.shape
    assert max(sizes) == 130 and sizes[-1] == 130


def test_mcmc_schedule_regulariser_and_errors():
    schedule = ScheduleConfig().resolve(3000)
    s = MCMCStrategy().setup(schedule)
    assert s.refine_stop_iter == 2500 and s.refine_every == schedule.refine_every
    with pytest.raises(StrategyError, match="cap_max"):
        MCMCStrategy(cap_max=None)
    with pytest.raises(StrategyError, match="noise mode"):
        MCMCStrategy(noise=PositionNoise(mode="sideways"))
    params = make_gaussians(20, torch.Generator().manual_seed(0))
    loss = s.regularization_loss(params)
    want = 0.01 * torch.sigmoid(params["opacities"]).mean() + 0.01 * torch.exp(params["scales"]).mean()
    assert torch.allclose(loss, want)
    loss.backward()
    assert params["opacities"].grad is not None and torch.count_nonzero(params["opacities"].grad) == 20
    empty = make_gaussians(0, torch.Generator().manual_seed(0))
    assert float(s.regularization_loss(empty)) == 0.0
    from exploregs_plugin.strategies import DefaultStrategy

    assert float(DefaultStrategy().regularization_loss(params)) == 0.0


def test_mcmc_hard_cases():
    gen = torch.Generator().manual_seed(0)
    s = MCMCStrategy(cap_max=50, **WINDOW)
    # N = 0
    empty = make_gaussians(0, gen)
    counts = s.step_post_backward(empty, make_optimizers(empty), s.initialize_state(), 10, _info(0), lr=1e-4, generator=gen)
    assert counts == {"relocated": 0, "added": 0, "perturbed": 0}
    # Everything dead: nothing to relocate onto; no crash, nothing deleted.
    params = make_gaussians(30, gen)
    with torch.no_grad():
        params["opacities"].fill_(-20.0)
    counts = s.step_post_backward(params, make_optimizers(params), s.initialize_state(), 10, _info(30), lr=1e-4, generator=gen)
    assert counts["relocated"] == 0 and params["means"].shape[0] == 31
    # A NaN opacity counts as dead and is relocated onto a finite Gaussian.
    params = make_gaussians(30, gen)
    with torch.no_grad():
        params["opacities"][3] = float("nan")
    counts = s.step_post_backward(params, make_optimizers(params), s.initialize_state(), 10, _info(30), lr=1e-4, generator=gen)
    assert counts["relocated"] == 1 and all(torch.isfinite(p).all() for p in params.values())


# ------------------------------------------------------------------------------ gsplat agreement
def test_agrees_with_gsplat_mcmc_ops(monkeypatch):
    """gsplat 1.5.3 has no torch backend for its relocation kernel (no GSPLAT_MCMC_BACKEND switch;
    compute_relocation is CUDA-only) and its covariance helper is CUDA-only too. We substitute
    the paper's formula evaluated directly (and gsplat's own torch covariance), and compare
    everything else gsplat's MCMC step does on CPU: sampling, relocation, growth and noise."""
    pytest.importorskip("gsplat")
    import gsplat.strategy.mcmc as gmcmc
    import gsplat.strategy.ops as gops
    from gsplat.cuda._torch_impl import _quat_scale_to_covar_preci

    def direct_relocation(opacities, scales, ratios, binoms):
        n_max = binoms.shape[0]
        new_o, coeff = [], []
        for o, n in zip(opacities.tolist(), ratios.clamp(1, n_max).tolist()):
            no, ns = _direct_relocation(o, 1.0, int(n))
            new_o.append(no)
            coeff.append(ns)
        return (torch.tensor(new_o, dtype=opacities.dtype),
                scales * torch.tensor(coeff, dtype=scales.dtype)[:, None])

    monkeypatch.setattr(gops, "compute_relocation", direct_relocation)
    monkeypatch.setattr(gops, "quat_scale_to_covar_preci", _quat_scale_to_covar_preci)

    g = torch.Generator().manual_seed(11)
    params = make_gaussians(300, g)
    with torch.no_grad():
        params["opacities"][torch.randperm(300, generator=g)[:60]] = -9.0
    optimizers = make_optimizers(params)
    adam_steps(params, optimizers, g)
    dead = (torch.sigmoid(params["opacities"].detach()) <= 0.005).clone()
    theirs_params = copy.deepcopy(params)
    theirs_opt = make_optimizers(theirs_params)
    for name in params:  # same saved moments on both sides
        theirs_opt[name].load_state_dict(copy.deepcopy(optimizers[name].state_dict()))

    kw = dict(refine_start_iter=2, refine_stop_iter=500, refine_every=10)
    ours = MCMCStrategy(cap_max=310, reset_every=100, **kw)
    theirs = gmcmc.MCMCStrategy(cap_max=310, noise_lr=5e5, min_opacity=0.005, **kw)
    ours_state, theirs_state = ours.initialize_state(), theirs.initialize_state()
    lr = 1.6e-4
    for step in (10, 11):  # a refinement step, then a noise-only step
        torch.manual_seed(100 + step)
        theirs.step_post_backward(theirs_params, theirs_opt, theirs_state, step, {}, lr=lr)
        ours.step_post_backward(params, optimizers, ours_state, step, _info(params["means"].shape[0]), lr=lr,
                                generator=torch.Generator().manual_seed(100 + step))
    assert params["means"].shape[0] == theirs_params["means"].shape[0] == 310
    for name in params:
        assert torch.allclose(params[name], theirs_params[name], rtol=1e-5, atol=1e-6), name
    # Moments agree except on the relocated rows, which gsplat leaves with their stale moments
    # while we zero them (they are new Gaussians).
    keep = torch.cat([~dead, torch.ones(10, dtype=torch.bool)])
    for name in params:
        ours_m = optimizers[name].state[params[name]]["exp_avg"]
        theirs_m = theirs_opt[name].state[theirs_params[name]]["exp_avg"]
        assert torch.allclose(ours_m[keep], theirs_m[keep]), name
        assert torch.count_nonzero(ours_m[torch.cat([dead, torch.zeros(10, dtype=torch.bool)])]) == 0
