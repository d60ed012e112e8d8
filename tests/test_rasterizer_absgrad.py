"""The absolute gradient sums (AbsGS; ``RasterSettings.absgrad``): per Gaussian and axis, the sum
over the pixels of |dL/dmean2d| of each pixel, left on ``info["means2d"].absgrad`` by both CPU
renderers, Default's ``absgrad`` statistic that reads them, and its ``split_absgrad2d`` (AbsGS's
split beside 3DGS's clone), which keeps them beside the summed gradient."""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch

from exploregs_plugin.bench.components.raster_scenes import random_scene
from exploregs_plugin.engine.pipeline import gather_observations, renderer_for
from exploregs_plugin.model import GaussianModelConfig
from exploregs_plugin.rasterizer import RasterSettings, rasterize
from exploregs_plugin.runtime.distributed import World
from exploregs_plugin.strategies.default import DefaultStrategy, grow_masks, ndc_gradient_norms
from exploregs_plugin.strategies.errors import StrategyError
from exploregs_plugin.strategies.observation import observe_render
from exploregs_plugin.strategies.requirements import ABSOLUTE_GRADIENT

F64 = torch.float64
WIDTH, HEIGHT = 20, 14


def _render(settings: RasterSettings, dtype=F64):
    """A scene of large, overlapping Gaussians (so that pixels pull a centre in different
    directions), its render and a fixed random weighting of the image: (params, image, info, weights)."""
    scene = random_scene(10, WIDTH, HEIGHT, torch.Generator().manual_seed(3), scale_range=(0.05, 0.4), dtype=dtype)
    params = [t.detach().clone().requires_grad_() for t in (scene.means, scene.quats, scene.scales,
                                                           scene.opacities, scene.sh_coeffs)]
    image, _, _, info = rasterize(*params, scene.camera, settings=settings)
    info["means2d"].retain_grad()
    weights = torch.randn(HEIGHT, WIDTH, 3, generator=torch.Generator().manual_seed(4), dtype=F64).to(dtype)
    return params, image, info, weights


@pytest.mark.usefixtures("raster_backend")
def test_the_sums_are_each_pixels_gradient_made_absolute_and_added():
    _, image, info, weights = _render(RasterSettings(absgrad=True))
    means2d = info["means2d"]
    (image * weights).sum().backward(retain_graph=True)
    sums, summed = means2d.absgrad.clone(), means2d.grad.clone()
    per_pixel, signed = torch.zeros_like(means2d), torch.zeros_like(means2d)
    for y in range(HEIGHT):
        for x in range(WIDTH):
            only = torch.zeros_like(weights)
            only[y, x] = weights[y, x]
            (grad,) = torch.autograd.grad(image, means2d, grad_outputs=only, retain_graph=True)
            per_pixel += grad.abs()
            signed += grad
    assert sums.shape == means2d.shape and sums.dtype == F64
    drawn = info["visible"]
    assert int(drawn.sum()) >= 6 and bool((sums[~drawn] == 0).all())
    torch.testing.assert_close(signed, summed, rtol=1e-9, atol=1e-12)  # the pixels' parts of the gradient
    torch.testing.assert_close(sums, per_pixel, rtol=1e-9, atol=1e-12)
    # the pixels pull the large Gaussians apart: some sums are well above the summed gradient's size
    assert float((sums[drawn] / summed[drawn].abs().clamp_min(1e-30)).max()) > 2.0


@pytest.mark.usefixtures("raster_backend")
def test_asking_for_the_sums_changes_no_gradient_and_their_bits_do_not_follow_the_thread_count():
    runs = {}
    before = torch.get_num_threads()
    try:
        for absgrad, threads in ((False, 1), (True, 1), (True, 2)):
            torch.set_num_threads(threads)
            params, image, info, weights = _render(RasterSettings(absgrad=absgrad), dtype=torch.float32)
            (image * weights).sum().backward()
            runs[absgrad, threads] = ([p.grad for p in params] + [info["means2d"].grad],
                                      getattr(info["means2d"], "absgrad", None))
    finally:
        torch.set_num_threads(before)
    plain, with_sums, two_threads = runs[False, 1], runs[True, 1], runs[True, 2]
    assert plain[1] is None  # not asked for: not made
    assert all(torch.equal(a, b) for a, b in zip(plain[0], with_sums[0]))
    assert all(torch.equal(a, b) for a, b in zip(with_sums[0], two_threads[0]))
    assert torch.equal(with_sums[1], two_threads[1])


def test_default_with_absgrad_asks_the_renderer_for_the_sums_and_grows_by_them():
    strategy = DefaultStrategy(absgrad=True)
    assert ABSOLUTE_GRADIENT in strategy.requirements() and ABSOLUTE_GRADIENT not in DefaultStrategy().requirements()
    assert renderer_for(GaussianModelConfig(), strategy.requirements()).raster.absgrad
    assert not renderer_for(GaussianModelConfig(), DefaultStrategy().requirements()).raster.absgrad

    _, image, info, weights = _render(RasterSettings(absgrad=True), dtype=torch.float32)
    (image * weights).sum().backward()
    n = info["means2d"].shape[0]
    for absgrad in (False, True):
        s = replace(strategy, absgrad=absgrad, refine_start_iter=0, refine_every=100, refine_stop_iter=1000, reset_every=3000)
        state = s.initialize_state()
        s.step_post_backward({"means": torch.zeros(n, 3)}, {}, state, 1, [observe_render(info)])
        read = info["means2d"].absgrad if absgrad else info["means2d"].grad
        expected = torch.where(info["visible"], ndc_gradient_norms(read, WIDTH, HEIGHT), 0.0)
        assert torch.equal(state["stats"]["grad2d"], expected)

    # a rank's view travels with its sums (every rank's strategy reads the same bits)
    (gathered,) = gather_observations(World(), [observe_render(info)], n, absolute=True)
    assert gathered.means2d is None and torch.equal(gathered.screen_gradient(absolute=True), info["means2d"].absgrad)


def test_a_view_rendered_without_the_sums_is_one_clear_error():
    _, image, info, weights = _render(RasterSettings(), dtype=torch.float32)
    (image * weights).sum().backward()
    with pytest.raises(StrategyError, match=r"no absolute gradient sums .*RasterSettings\(absgrad=True\)"):
        observe_render(info).screen_gradient(absolute=True)


def test_grow_masks_split_a_large_gaussian_by_the_absolute_sums_and_clone_by_the_gradient_alone():
    # rows: small with a high gradient, large with a high gradient, large with only the sums high,
    # small with only the sums high, large with both low, large with the sums at the threshold
    avg_grad = torch.tensor([3e-4, 3e-4, 1e-4, 1e-4, 1e-4, 1e-4])
    avg_abs = torch.tensor([5e-4, 5e-4, 2e-3, 2e-3, 5e-4, 1e-3])
    small, large = torch.log(torch.full((3,), 0.005)), torch.log(torch.full((3,), 0.5))
    log_scales = torch.stack([small, large, large, small, large, large])
    plain = grow_masks(avg_grad, log_scales, 2e-4, 0.01)
    clone, split = grow_masks(avg_grad, log_scales, 2e-4, 0.01, avg_abs, 1e-3)
    assert clone.tolist() == plain[0].tolist() == [True, False, False, False, False, False]
    assert plain[1].tolist() == [False, True, False, False, False, False]
    assert split.tolist() == [False, True, True, False, False, False]


def test_split_absgrad2d_keeps_the_sums_beside_the_gradient_and_splits_by_them():
    strategy = DefaultStrategy(split_absgrad2d=1e-3)
    assert strategy.splits_by_absolute_sums() and ABSOLUTE_GRADIENT in strategy.requirements()
    for bad in (0.0, -1e-3, float("nan")):
        with pytest.raises(StrategyError, match="split_absgrad2d must be positive"):
            DefaultStrategy(split_absgrad2d=bad)
    with pytest.raises(StrategyError, match="set one of the two"):  # absgrad's growth reads the sums already
        replace(strategy, absgrad=True)

    _, image, info, weights = _render(RasterSettings(absgrad=True), dtype=torch.float32)
    (image * weights).sum().backward()
    n, visible = info["means2d"].shape[0], info["visible"]
    s = replace(strategy, refine_start_iter=0, refine_every=2, refine_stop_iter=1000, reset_every=3000)
    state = s.initialize_state()
    state["scene_scale"] = 1.0
    params = {"means": torch.zeros(n, 3), "scales": torch.log(torch.full((n, 3), 0.5))}  # every row too large to clone
    s.step_post_backward(params, {}, state, 1, [observe_render(info)])
    stats = state["stats"]
    for key, read in (("grad2d", info["means2d"].grad), ("absgrad2d", info["means2d"].absgrad)):
        assert torch.equal(stats[key], torch.where(visible, ndc_gradient_norms(read, WIDTH, HEIGHT), 0.0))
    assert torch.equal(stats["abscount"], stats["count"])
    # a threshold between the two statistics of a row splits it by its sums alone
    ratio = stats["absgrad2d"] / stats["grad2d"].clamp_min(1e-30)
    row = int(torch.argmax(torch.where(visible, ratio, 0.0)))
    between = float(stats["grad2d"][row] + stats["absgrad2d"][row]) / 2
    s = replace(s, grow_grad2d=between, split_absgrad2d=between)
    clone, split = s.growth(params, state)
    assert not clone.any() and bool(split[row])
    assert bool(split[row]) != bool((replace(s, split_absgrad2d=None).growth(params, state))[1][row])


def test_a_run_with_split_absgrad2d_splits_more_and_starts_each_window_with_empty_sums(tmp_path, tiny_scene_dir):
    from exploregs_plugin.callbacks import TrainingCallback
    from exploregs_plugin.method_configs import get_method
    from exploregs_plugin.schedule import ScheduleConfig

    class Sums(TrainingCallback):
        def __init__(self):
            self.after = {}

        def after_step(self, trainer, step, stats):
            sums = trainer.pipeline.strategy_state["stats"].get("absgrad2d")
            self.after[step] = (None if sums is None else float(sums.abs().sum()), stats["counts"].get("split", 0))

    config = get_method("exploregs-default").config
    splits = {}
    for threshold in (None, 1e-3):
        strategy = replace(config.pipeline.strategy, split_absgrad2d=threshold)
        run = replace(config, data="builtin:tiny", max_steps=31, run_dir=tmp_path / f"run-{threshold}", quiet=True,
                      tensorboard=False, eval_count=1, save_eval_images=False, num_threads=1,
                      schedule=ScheduleConfig(min_refine_every=10),
                      pipeline=replace(config.pipeline, strategy=strategy))
        sums = Sums()
        run.setup(callbacks=[sums]).train()
        splits[threshold] = sum(split for _, split in sums.after.values())
        if threshold is None:
            assert all(total is None for total, _ in sums.after.values())  # no sums asked for, none kept
        else:  # the refinement of step 10 (the callback's step 11) clears them with grad2d; the next view adds
            assert sums.after[10][0] > 0.0 and sums.after[11] == (0.0, splits[threshold]) and sums.after[12][0] > 0.0
    assert splits[1e-3] > splits[None]
