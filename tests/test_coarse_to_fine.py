"""Coarse-to-fine training: the schedule's levels, the datamanager's downscaled views, and the
densification statistic that means the same at every level (docs/training.md, "Coarse to fine")."""

from __future__ import annotations

import json

import pytest
import torch

from exploregs_plugin.cameras import Camera
from exploregs_plugin.data.datamanager import DataManagerConfig
from exploregs_plugin.rasterizer import rasterize
from exploregs_plugin.schedule import SHORT_FRACTIONS, ScheduleConfig
from exploregs_plugin.strategies.default import accumulate_grad_stats, ndc_gradient_norms
from exploregs_plugin.strategies.observation import observe_render
from exploregs_plugin.engine.trainer import TrainerConfig


# ---------------------------------------------------------------------------- schedule
def test_levels_double_the_resolution_every_interval_until_full():
    schedule = ScheduleConfig(coarse_levels=2, coarse_every_frac=0.1).resolve(1000)
    assert schedule.coarse_every == 100
    assert [schedule.downscale_at(t) for t in (0, 99, 100, 199, 200, 999)] == [4, 4, 2, 2, 1, 1]
    assert {ScheduleConfig().resolve(1000).downscale_at(t) for t in range(0, 1000, 7)} == {1}


def test_levels_count_images_seen_with_a_batch():
    # 1000 steps of 4 views: a level lasts a tenth of the 4000 images, i.e. 100 steps
    schedule = ScheduleConfig(coarse_levels=1, coarse_every_frac=0.1).resolve(1000, views_per_step=4)
    assert schedule.coarse_every == 100 and schedule.downscale_at(99) == 2 and schedule.downscale_at(100) == 1


def test_the_short_schedule_is_3dgs_at_7k_scaled_to_the_run():
    schedule = ScheduleConfig(name="short").resolve(7000)
    # 3DGS's own step numbers at 7000 steps: densify from 500 (and on past the end), every 100,
    # reset every 3000, SH degree up every 1000
    assert (schedule.refine_start, schedule.refine_every, schedule.reset_every, schedule.sh_degree_interval) == (
        500, 100, 3000, 1000)
    assert schedule.refine_stop >= schedule.max_steps
    assert ScheduleConfig(name="short").fractions() == SHORT_FRACTIONS
    assert ScheduleConfig().resolve(7000).refine_stop == 3500  # the 3dgs schedule stops at half


@pytest.mark.parametrize("kwargs, message", [
    ({"coarse_levels": -1}, "coarse_levels must be >= 0, got -1"),
    ({"coarse_every_frac": 0.0}, "coarse_every_frac must be in (0, 1], got 0.0"),
    ({"name": "7k"}, "schedule name must be one of 3dgs, short, got '7k'"),
])
def test_bad_schedule_values_are_one_line(kwargs, message):
    with pytest.raises(ValueError) as err:
        ScheduleConfig(**kwargs)
    assert str(err.value) == message


# ---------------------------------------------------------------------------- data
def test_a_coarse_view_is_the_box_filtered_image_with_its_camera_scaled():
    dm = DataManagerConfig(data="builtin:tiny").setup()
    camera, image, extras = dm.train_item(0)
    small_camera, small, small_extras = dm.train_item(0, None, 2)
    h, w = camera.height // 2, camera.width // 2
    assert (small_camera.width, small_camera.height) == (w, h) and small.shape == (h, w, 3)
    # the image: the mean of each 2x2 block (to the 8-bit rounding of the stored pixels)
    block_mean = image.reshape(h, 2, w, 2, 3).mean(dim=(1, 3))
    assert float((small - block_mean).abs().max()) <= 1.0 / 255.0 + 1e-6
    # the camera: a world point lands at u / 2 with pixel centres at +0.5, i.e. the centre
    # (2j + 1) of a block of the full image is the centre j + 0.5 of the small one
    point = torch.tensor([0.1, -0.2, 0.3, 1.0])
    def project(cam: Camera) -> torch.Tensor:
        x = (cam.viewmat @ point)[:3]
        uvw = cam.K @ x
        return uvw[:2] / uvw[2]
    assert torch.allclose(project(small_camera), project(camera) / 2, atol=1e-5)
    assert torch.equal(small_camera.viewmat, camera.viewmat)
    assert small_extras["depth"].shape == (h, w, 1) and all(m.shape == (h, w) for m in small_extras["masks"].values())
    # cached: the second call gives the same tensors
    assert torch.equal(dm.train_item(0, None, 2)[1], small)


# ---------------------------------------------------------------------------- the statistic
def test_ndc_norm_at_a_level_is_divided_by_its_downscale():
    grads = torch.tensor([[[3e-4, -4e-4], [1e-5, 0.0]]])
    full = ndc_gradient_norms(grads, 64, 48)
    assert torch.equal(ndc_gradient_norms(grads, 64, 48, downscale=1), full)
    assert torch.allclose(ndc_gradient_norms(grads, 64, 48, downscale=4), full / 4)
    stats: dict[str, torch.Tensor] = {}
    accumulate_grad_stats(stats, grads, torch.ones(1, 2, dtype=torch.bool), 64, 48, downscale=2)
    assert torch.allclose(stats["grad2d"], full[0] / 2)


def _edge_scene(world_sigma: float, size: int) -> tuple[dict[str, torch.Tensor], Camera, torch.Tensor]:
    """A row of Gaussians on the vertical edge of a black | white target, seen by a size x size
    camera at distance 4 (focal = size: one pixel spans 4 / size world units at the Gaussians)."""
    n = 4
    ys = torch.linspace(-0.9, 0.9, n)  # 0.6 apart: 19 px at 128 px, still 4.8 px at 32
    means = torch.stack([torch.zeros(n), ys, torch.zeros(n)], dim=-1)
    params = {
        "means": means.clone().requires_grad_(True),
        "quats": torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1),
        "scales": torch.full((n, 3), world_sigma),
        "opacities": torch.full((n,), 0.8),
        "colors": torch.full((n, 3), 0.3),
    }
    viewmat = torch.eye(4)
    viewmat[2, 3] = 4.0
    K = torch.tensor([[float(size), 0.0, size / 2.0], [0.0, float(size), size / 2.0], [0.0, 0.0, 1.0]])
    target = torch.zeros(size, size, 3)
    target[:, size // 2:] = 1.0
    return params, Camera(viewmat, K, size, size), target


def _statistic(world_sigma: float, size: int, downscale: int) -> torch.Tensor:
    """Default's per-Gaussian statistic of the L1 loss, rendered at size / downscale."""
    params, camera, target = _edge_scene(world_sigma, size)
    small = size // downscale
    camera = camera.scaled(1.0 / downscale, (small, small))
    target = target.reshape(small, downscale, small, downscale, 3).mean(dim=(1, 3))
    image, _, _, info = rasterize(params["means"], params["quats"], params["scales"], params["opacities"], None,
                                  camera, colors=params["colors"], background=torch.full((3,), 0.5))
    view = observe_render(info, downscale=downscale)
    view.keep_gradient("test")
    (image - target).abs().mean().backward()
    stats: dict[str, torch.Tensor] = {}
    n = params["means"].shape[0]
    accumulate_grad_stats(stats, view.screen_gradient().reshape(1, n, 2), view.visible().reshape(1, n),
                          view.width, view.height, view.n_cameras, view.downscale)
    assert bool((stats["count"] == 1).all())
    return stats["grad2d"]


@pytest.mark.parametrize("downscale", [2, 4])
def test_a_pixel_sized_gaussian_has_the_same_statistic_at_every_level(downscale):
    """Gaussians far below a pixel at both sizes (the rasterizer's 0.3 px^2 blur gives them one
    pixel's footprint at every level): their NDC gradient grows as 1 / H, which the division by
    the level's downscale undoes (within 3%; without it, downscale times as large)."""
    full = _statistic(0.002, 128, 1)  # sigma 0.06 px at 128 px
    coarse = _statistic(0.002, 128, downscale)
    assert float(full.min()) > 0.0
    ratio = coarse / full
    assert torch.allclose(ratio, torch.ones_like(ratio), rtol=0.03), ratio


@pytest.mark.parametrize("downscale", [2, 4])
def test_a_gaussian_of_many_pixels_has_1_over_s_of_its_statistic(downscale):
    """The other limit of the derivation: a Gaussian of many pixels at every level has the same NDC
    gradient at every level, so the divided statistic is 1 / s of it (to 5%): coarse levels
    densify large Gaussians less, never more."""
    full = _statistic(0.25, 128, 1)  # sigma 8 px at 128 px, 2 px at 32
    coarse = _statistic(0.25, 128, downscale)
    ratio = coarse / full
    assert torch.allclose(ratio, torch.full_like(ratio, 1.0 / downscale), rtol=0.05), ratio


# ---------------------------------------------------------------------------- training
def test_a_coarse_to_fine_run_trains_and_evaluates_at_full_size(tmp_path):
    config = TrainerConfig(data="builtin:tiny", max_steps=40, run_dir=tmp_path / "run", eval_count=2,
                           tensorboard=False, save_eval_images=False, quiet=True,
                           schedule=ScheduleConfig(coarse_levels=2, coarse_every_frac=0.25, min_refine_every=10))
    trainer = config.setup()
    sizes = []
    render = trainer.pipeline.model.render

    def spy(camera, *args, **kwargs):
        sizes.append((camera.width, camera.height))
        return render(camera, *args, **kwargs)

    trainer.pipeline.model.render = spy
    restarts = []
    update = trainer.watches.collapse.update

    def watch(step, psnr, loss, restart=False, view=None):
        restarts.append((step, restart))
        return update(step, psnr, loss, restart=restart, view=view)

    trainer.watches.collapse.update = watch
    metrics = trainer.train()
    # the collapse watch starts afresh after the last step of each level (its training PSNR is of
    # easier targets than the next level's): steps 9 and 19, and no other step before the last but
    # the settled cut's (after step 32: the cut may remove a tenth of the set, a deliberate setback
    # too, as the end-of-run cut at the last)
    assert trainer.pipeline.strategy.settled_cut_iter == 32
    assert [step for step, restart in restarts if restart and step not in (31, 39)] == [9, 19]
    # steps 0-9 at 16x12, 10-19 at 32x24, 20-39 at 64x48; evaluations (steps 20, 40) at 64x48
    assert sizes[:10] == [(16, 12)] * 10 and sizes[10:20] == [(32, 24)] * 10
    assert all(s == (64, 48) for s in sizes[20:])
    saved = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert saved["psnr"] == metrics["psnr"] and metrics["psnr"] > 10.0

