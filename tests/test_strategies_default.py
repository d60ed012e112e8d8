"""Default strategy (3DGS adaptive density control): statistics, decisions, gsplat parity."""

from __future__ import annotations

import copy

import pytest
import torch

from exploregs_plugin.cameras import Camera
from exploregs_plugin.schedule import ScheduleConfig
from exploregs_plugin.strategies import DefaultStrategy, StrategyError, row_ops
from exploregs_plugin.strategies.default import accumulate_grad_stats, ndc_gradient_norms
from exploregs_plugin.strategies.observation import ViewObservation, observe_render
from exploregs_plugin.strategies.synthetic import make_gaussians, make_optimizers, synthetic_views

W, H = 64, 48


def _strategy(**kw) -> DefaultStrategy:
    base = dict(refine_start_iter=5, refine_stop_iter=1000, refine_every=10, reset_every=30)
    base.update(kw)
    return DefaultStrategy(**base)


def test_setup_fills_schedule_fields_only_when_none():
    schedule = ScheduleConfig().resolve(3000)
    s = DefaultStrategy(refine_every=7).setup(schedule)
    assert s.refine_every == 7
    assert (s.refine_start_iter, s.refine_stop_iter, s.reset_every) == (
        schedule.refine_start, schedule.refine_stop, schedule.reset_every)
    with pytest.raises(StrategyError, match="setup"):
        g = torch.Generator().manual_seed(0)
        params = make_gaussians(3, g)
        DefaultStrategy().step_post_backward(params, make_optimizers(params), DefaultStrategy().initialize_state(), 1, {})


def test_grad_statistic_is_ndc_norm_averaged_over_visible_views():
    g = torch.Generator().manual_seed(0)
    params = make_gaussians(3, g)
    optimizers = make_optimizers(params)
    s = _strategy()
    state = s.initialize_state(scene_scale=1.0)
    grads = [torch.tensor([[1e-5, 0.0], [0.0, 2e-5], [3e-5, 4e-5]]), torch.tensor([[3e-5, 0.0], [9.0, 9.0], [0.0, 0.0]])]
    vis = [torch.tensor([True, True, True]), torch.tensor([True, False, True])]
    for step, (gr, v) in enumerate(zip(grads, vis), start=1):
        s.step_post_backward(params, optimizers, state, step, synthetic_views(gr, v, W, H))
    stats = state["stats"]
    assert torch.equal(stats["count"], torch.tensor([2.0, 1.0, 2.0]))
    expected = torch.tensor([
        1e-5 * W / 2 + 3e-5 * W / 2,
        2e-5 * H / 2,
        ((3e-5 * W / 2) ** 2 + (4e-5 * H / 2) ** 2) ** 0.5,
    ])
    assert torch.allclose(stats["grad2d"], expected, rtol=1e-6)


def test_nonfinite_gradients_are_skipped_and_counted():
    g = torch.Generator().manual_seed(0)
    params = make_gaussians(4, g)
    s = _strategy()
    state = s.initialize_state()
    gr = torch.tensor([[1e-5, 0.0], [float("nan"), 0.0], [float("inf"), 1.0], [1e-5, 1e-5]])
    counts = s.step_post_backward(params, make_optimizers(params), state, 1, synthetic_views(gr, torch.ones(4, dtype=torch.bool), W, H))
    assert counts["nonfinite_grads"] == 2
    assert torch.equal(state["stats"]["count"], torch.tensor([1.0, 0.0, 0.0, 1.0]))
    assert torch.isfinite(state["stats"]["grad2d"]).all()


def test_one_cameras_statistic_is_the_same_bits_as_a_batch_of_one():
    """The step's [N, 2] gradient is accumulated as it is (no reshape into a camera batch): the
    same sums and counts as the [1, N, 2] form, and a non-finite gradient counts as skipped only
    where the view drew the Gaussian; two cameras add in camera order."""
    g = torch.Generator().manual_seed(3)
    grads = torch.randn(2, 6, 2, generator=g) * 1e-4
    grads[0, 1, 0], grads[0, 2, 1], grads[1, 4, 0] = float("nan"), float("inf"), float("-inf")
    visible = torch.tensor([[True, True, False, True, True, False], [True, False, True, True, True, True]])
    flat, batch, two = {}, {}, {}
    for stats, pixel_grads, vis in ((flat, grads[0], visible[0]), (batch, grads[:1], visible[:1])):
        skipped = accumulate_grad_stats(stats, pixel_grads, vis, W, H, n_cameras=2, downscale=2, reference_height=96)
        assert int(skipped) == 1  # row 1 (drawn, NaN); row 2's inf was not drawn
    assert torch.equal(flat["grad2d"], batch["grad2d"]) and torch.equal(flat["count"], batch["count"])
    assert torch.equal(flat["count"], torch.tensor([1.0, 0.0, 0.0, 1.0, 1.0, 0.0]))
    assert int(accumulate_grad_stats(two, grads, visible, W, H)) == 2  # (0, 1) and (1, 4)
    expected = torch.zeros(6)
    for camera in range(2):
        norms = ndc_gradient_norms(grads[camera], W, H)
        expected += torch.where(visible[camera] & torch.isfinite(norms), norms, 0.0)
    assert torch.equal(two["grad2d"], expected)


def test_missing_retain_grad_is_a_clear_error():
    g = torch.Generator().manual_seed(0)
    params = make_gaussians(2, g)
    s = _strategy()
    means2d = torch.zeros(2, 2, requires_grad=True) * 1.0  # non-leaf, grad not retained
    view = ViewObservation(W, H, torch.ones(2, 2, dtype=torch.int32), torch.zeros(3), means2d=means2d)
    with pytest.raises(StrategyError, match="step_pre_backward"):
        s.step_post_backward(params, make_optimizers(params), s.initialize_state(), 1, [view])
    s.step_pre_backward(params, {}, {}, 1, view)
    assert means2d.retains_grad


def test_a_render_info_dict_is_refused_with_the_way_to_an_observation():
    """Strategies receive a list of ViewObservation; a raw info dict (or an empty list) gets one
    line naming the type and observe_render."""
    g = torch.Generator().manual_seed(0)
    params = make_gaussians(2, g)
    s = _strategy()
    view = synthetic_views(torch.zeros(2, 2), torch.ones(2, dtype=torch.bool), W, H)[0]
    for bad in ({"means2d": view.means2d, "radii": view.radii, "width": W, "height": H}, view, []):
        with pytest.raises(StrategyError, match="list of .*ViewObservation.*observe_render"):
            s.step_post_backward(params, make_optimizers(params), s.initialize_state(), 1, bad)


def _scene(n: int, seed: int, scene_scale: float):
    """Gaussians whose sizes straddle the clone/split and size-prune thresholds."""
    g = torch.Generator().manual_seed(seed)
    params = make_gaussians(n, g, sh_degree=1, extent=scene_scale)
    with torch.no_grad():
        # Largest scale, as a fraction of the extent: a quarter below 0.01 (clone), half between
        # 0.01 and 0.1 (split), a quarter above 0.1 (size prune after the first reset).
        frac = torch.empty(n)
        q = n // 4
        frac[:q] = torch.empty(q).uniform_(0.002, 0.009, generator=g)
        frac[q:3 * q] = torch.empty(2 * q).uniform_(0.012, 0.09, generator=g)
        frac[3 * q:] = torch.empty(n - 3 * q).uniform_(0.12, 0.5, generator=g)
        ratios = torch.empty(n, 3).uniform_(0.2, 1.0, generator=g)
        ratios[torch.arange(n), torch.randint(0, 3, (n,), generator=g)] = 1.0
        params["scales"].copy_(torch.log(frac[:, None] * ratios * scene_scale))
        params["opacities"].copy_(torch.empty(n).uniform_(-4.0, 4.0, generator=g))
        params["opacities"][torch.randperm(n, generator=g)[: n // 8]] = -7.0  # opacity < 0.005
    return g, params


def _grads(g: torch.Generator, n: int, base: torch.Tensor):
    """Per-view pixel gradients around a per-Gaussian magnitude, random visibility."""
    gr = base[:, None] * torch.randn(n, 2, generator=g)
    vis = torch.rand(n, generator=g) < 0.7
    return gr, vis


def test_reset_opacity_and_size_prune_timing():
    g, params = _scene(40, seed=1, scene_scale=1.0)
    optimizers = make_optimizers(params)
    s = _strategy(grow_grad2d=1e9)  # no growth: isolate pruning and reset
    state = s.initialize_state(scene_scale=1.0)
    def zero_info():
        n = params["means"].shape[0]
        return synthetic_views(torch.zeros(n, 2), torch.ones(n, dtype=torch.bool), W, H)

    big = (torch.exp(params["scales"].detach()).max(-1).values > 0.1)
    faint = torch.sigmoid(params["opacities"].detach()) < 0.005
    counts = s.step_post_backward(params, optimizers, state, 10, zero_info())  # before first reset
    assert counts["pruned"] == int(faint.sum()) and counts["opacity_reset"] == 0 and "pruned_too_big" not in counts
    n_before = params["means"].shape[0]
    counts = s.step_post_backward(params, optimizers, state, 30, zero_info())  # reset step
    assert counts["opacity_reset"] == 1
    assert torch.all(torch.sigmoid(params["opacities"].detach()) <= 0.01 + 1e-6)
    assert params["means"].shape[0] == n_before  # opacities were clamped to 0.01 >= 0.005: kept
    counts = s.step_post_backward(params, optimizers, state, 40, zero_info())  # after reset: size prune on
    assert counts["pruned"] == int((big & ~faint).sum()) > 0
    assert counts["pruned_too_big"] == int((big & ~faint).sum())  # said apart, for the collapse watch's restart
    assert torch.all(torch.exp(params["scales"].detach()).max(-1).values <= 0.1)
    # Past refine_stop nothing happens at all.
    n = params["means"].shape[0]
    counts = s.step_post_backward(params, optimizers, state, 1000, zero_info())
    assert params["means"].shape[0] == n and counts["opacity_reset"] == 0


def test_cap_max_limits_growth_to_highest_gradients():
    g, params = _scene(80, seed=2, scene_scale=1.0)
    with torch.no_grad():
        params["opacities"].clamp_(min=0.0)
    optimizers = make_optimizers(params)
    s = _strategy(cap_max=85, prune_scale3d=1e9)
    state = s.initialize_state()
    base = torch.linspace(1e-6, 4e-5, 80)
    info = synthetic_views(base[:, None].expand(80, 2).contiguous(), torch.ones(80, dtype=torch.bool), W, H)
    counts = s.step_post_backward(params, optimizers, state, 10, info, generator=torch.Generator().manual_seed(0))
    assert counts["cloned"] + counts["split"] == 5
    assert params["means"].shape[0] == 85


def test_split_requires_a_generator():
    g, params = _scene(40, seed=3, scene_scale=1.0)
    s = _strategy()
    state = s.initialize_state()
    info = synthetic_views(torch.full((40, 2), 1e-3), torch.ones(40, dtype=torch.bool), W, H)
    with pytest.raises(StrategyError, match="generator"):
        s.step_post_backward(params, make_optimizers(params), state, 10, info)


def test_all_pruned_then_empty_steps_do_not_crash():
    g, params = _scene(16, seed=4, scene_scale=1.0)
    with torch.no_grad():
        params["opacities"].fill_(-20.0)
    optimizers = make_optimizers(params)
    s = _strategy()
    state = s.initialize_state()
    info = synthetic_views(torch.full((16, 2), 1e-3), torch.ones(16, dtype=torch.bool), W, H)
    gen = torch.Generator().manual_seed(0)
    counts = s.step_post_backward(params, optimizers, state, 10, info, generator=gen)
    assert counts["pruned"] >= 16 - counts["cloned"] - counts["split"]
    assert params["means"].shape[0] == 0
    empty = synthetic_views(torch.zeros(0, 2), torch.zeros(0, dtype=torch.bool), W, H)
    for step in (11, 20, 30):
        s.step_post_backward(params, optimizers, state, step, empty, generator=gen)
    assert params["means"].shape[0] == 0


# ------------------------------------------------------------------------------ gsplat parity
def _import_gsplat_default():
    pytest.importorskip("gsplat")
    import gsplat.strategy.default as gdefault

    return gdefault


def test_parity_with_gsplat_default_strategy(monkeypatch):
    gdefault = _import_gsplat_default()
    n, scene_scale = 400, 2.0
    g, params = _scene(n, seed=7, scene_scale=scene_scale)
    ours = {"params": params, "optimizers": make_optimizers(params)}
    theirs_params = copy.deepcopy(params)
    theirs = {"params": theirs_params, "optimizers": make_optimizers(theirs_params)}

    kw = dict(refine_start_iter=5, refine_stop_iter=1000, refine_every=10, reset_every=30)
    ours_s = DefaultStrategy(**kw)
    theirs_s = gdefault.DefaultStrategy(prune_opa=0.005, grow_grad2d=0.0002, grow_scale3d=0.01,
                                        prune_scale3d=0.1, **kw)
    ours_state = ours_s.initialize_state(scene_scale=scene_scale)
    theirs_state = theirs_s.initialize_state(scene_scale=scene_scale)

    # Record the masks both implementations hand to their ops.
    recorded = {"ours": {}, "theirs": {}}

    def recorder(side, name, fn):
        def wrapped(*args, **kwargs):
            recorded[side][name] = kwargs["mask"].clone() if "mask" in kwargs else args[3].clone()
            if name == "remove":
                p = kwargs["params"] if "params" in kwargs else args[0]
                recorded[side]["faint"] = torch.sigmoid(p["opacities"].detach()) < 0.005
                recorded[side]["big"] = torch.exp(p["scales"].detach()).max(-1).values > 0.1 * scene_scale
            return fn(*args, **kwargs)
        return wrapped

    for name in ("duplicate", "split", "remove"):
        monkeypatch.setattr(gdefault, name, recorder("theirs", name, getattr(gdefault, name)))
        monkeypatch.setattr(row_ops, name, recorder("ours", name, getattr(row_ops, name)))

    base = torch.exp(torch.empty(n).uniform_(-14.5, -9.5, generator=g))  # pixel grads ~ 5e-7..7e-5
    for step in range(31, 41):  # steps 31..39 accumulate, 40 refines (after the first reset)
        gr, vis = _grads(g, n, base)
        info = synthetic_views(gr, vis, W, H)
        ginfo = {
            "means2d": torch.zeros(1, n, 2, requires_grad=True), "radii": info[0].radii[None],
            "width": W, "height": H, "n_cameras": 1, "gaussian_ids": None,
        }
        ginfo["means2d"].grad = gr[None].clone()
        if step == 40:
            assert torch.allclose(ours_state["stats"]["grad2d"], theirs_state["grad2d"], rtol=1e-6, atol=0)
            assert torch.equal(ours_state["stats"]["count"], theirs_state["count"])
            avg = theirs_state["grad2d"] / theirs_state["count"].clamp_min(1)
        torch.manual_seed(1234)  # gsplat draws split offsets from the global generator
        counts = ours_s.step_post_backward(ours["params"], ours["optimizers"], ours_state, step, info,
                                           generator=torch.Generator().manual_seed(1234))
        theirs_s.step_post_backward(theirs["params"], theirs["optimizers"], theirs_state, step, ginfo)

    # Each decision fires in non-trivial numbers, and the index sets are identical.
    for name in ("duplicate", "split", "remove"):
        assert torch.equal(recorded["ours"][name], recorded["theirs"][name]), name
    assert counts["cloned"] >= 20 and counts["split"] >= 20
    # Pruning: opacity and size criteria both fire (evaluated on the post-growth rows).
    removed = recorded["theirs"]["remove"]
    assert counts["pruned"] == int(removed.sum())
    assert torch.equal(recorded["ours"]["faint"], recorded["theirs"]["faint"])
    assert torch.equal(removed, recorded["theirs"]["faint"] | recorded["theirs"]["big"])
    assert int((recorded["theirs"]["faint"] & ~recorded["theirs"]["big"]).sum()) >= 20
    assert int((recorded["theirs"]["big"] & ~recorded["theirs"]["faint"]).sum()) >= 20
    assert (avg > 0.0002).sum() > 40 and (avg <= 0.0002).sum() > 40

    # Same Gaussians, same order, same values, same moments and statistics afterwards.
    assert ours["params"]["means"].shape[0] == theirs["params"]["means"].shape[0]
    for key in ours["params"]:
        assert torch.allclose(ours["params"][key], theirs["params"][key], atol=1e-6), key
    assert torch.equal(ours_state["stats"]["grad2d"], theirs_state["grad2d"])


def test_trainer_call_order_with_a_real_graph():
    """pre-backward retains the 2D-mean gradient; it survives optimizer.step and zero_grad and
    post-backward turns it into the NDC statistic (a toy pinhole projection stands in for the
    rasterizer)."""
    g = torch.Generator().manual_seed(0)
    params = make_gaussians(5, g)
    optimizers = make_optimizers(params)
    s = _strategy()
    state = s.initialize_state()
    focal, c = 40.0, torch.tensor([W / 2, H / 2])
    cam_z = params["means"][:, 2:3] + 3.0
    means2d = params["means"][:, :2] / cam_z * focal + c  # [N, 2] pixels, non-leaf
    view = ViewObservation(W, H, torch.full((5, 2), 2, dtype=torch.int32), torch.zeros(3), means2d=means2d)
    s.step_pre_backward(params, optimizers, state, 1, view)
    target = torch.randn(5, 2, generator=g)
    loss = ((means2d - c - target) ** 2).sum() * 1e-6
    loss.backward()
    pixel_grad = (2e-6 * (means2d - c - target)).detach()
    for opt in optimizers.values():
        opt.step()
        opt.zero_grad()
    counts = s.step_post_backward(params, optimizers, state, 1, [view], lr=1e-3, generator=g)
    assert counts["nonfinite_grads"] == 0
    scale = torch.tensor([W / 2, H / 2])
    assert torch.allclose(state["stats"]["grad2d"], (pixel_grad * scale).norm(dim=-1), rtol=1e-5)
    assert torch.equal(state["stats"]["count"], torch.ones(5))


def test_info_from_another_set_is_rejected():
    g = torch.Generator().manual_seed(0)
    params = make_gaussians(6, g)
    s = _strategy()
    stale = synthetic_views(torch.zeros(3, 2), torch.ones(3, dtype=torch.bool), W, H)
    with pytest.raises(StrategyError, match="6 Gaussians"):
        s.step_post_backward(params, make_optimizers(params), s.initialize_state(), 1, stale)


def test_default_with_the_project_rasterizer():
    """The real rasterizer's info drives the statistic and densification (16x16 toy scene)."""
    from exploregs_plugin.rasterizer import rasterize

    size = 16
    K = torch.tensor([[16.0, 0, 8.0], [0, 16.0, 8.0], [0, 0, 1]])
    view = torch.eye(4)
    view[2, 3] = 3.0
    g = torch.Generator().manual_seed(0)
    target_params = make_gaussians(8, g, sh_degree=0, extent=0.5)
    params = make_gaussians(12, g, sh_degree=0, extent=0.5)
    optimizers = make_optimizers(params, lr=1e-2)

    def render(p):
        return rasterize(p["means"], p["quats"], torch.exp(p["scales"]) * 4, torch.sigmoid(p["opacities"]),
                         torch.cat([p["sh0"], p["shN"]], 1), Camera(view, K, size, size))

    with torch.no_grad():
        target = render(target_params)[0]
    s = _strategy(refine_start_iter=0, refine_every=5)
    state = s.initialize_state(scene_scale=0.5)
    grown = 0
    for step in range(1, 6):
        n = params["means"].shape[0]
        image, _, _, info = render(params)
        seen = observe_render(info)
        s.step_pre_backward(params, optimizers, state, step, seen)
        (image - target).abs().mean().backward()
        for opt in optimizers.values():
            opt.step()
            opt.zero_grad()
        if step == 4:
            stats = state["stats"]
            assert stats["grad2d"].shape == (n,) and torch.isfinite(stats["grad2d"]).all()
            assert stats["count"].max() == 3 and float(stats["grad2d"].max()) > 0.0  # steps 1-3
        counts = s.step_post_backward(params, optimizers, state, step, [seen], lr=1e-3, generator=g)
        grown += counts["cloned"] + counts["split"]
    assert grown > 0
    s.check_sanity(params, optimizers)


def test_state_is_checkpointable_and_validated(tmp_path):
    g = torch.Generator().manual_seed(0)
    params = make_gaussians(5, g)
    s = _strategy()
    state = s.initialize_state(scene_scale=2.0, scene_center=torch.tensor([1.0, 2.0, 3.0]))
    s.step_post_backward(params, make_optimizers(params), state, 1,
                         synthetic_views(torch.full((5, 2), 1e-4), torch.ones(5, dtype=torch.bool), W, H))
    torch.save(state, tmp_path / "state.pt")
    loaded = torch.load(tmp_path / "state.pt")
    assert loaded["scene_scale"] == 2.0 and torch.equal(loaded["stats"]["grad2d"], state["stats"]["grad2d"])
    for bad in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(StrategyError, match="scene_scale"):
            s.initialize_state(scene_scale=bad)
    with pytest.raises(StrategyError, match="lack required keys"):
        s.check_sanity({"means": params["means"]}, {"means": torch.optim.Adam([params["means"]])})
    with pytest.raises(StrategyError, match="does not hold"):
        other = make_optimizers(make_gaussians(5, g))
        s.check_sanity(params, other)
