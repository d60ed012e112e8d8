"""Gradient branches: finite differences per path, sum = total, directions, the training logger."""

from __future__ import annotations

import math

import pytest
import torch

from exploregs_plugin.rasterizer import RasterSettings

from exploregs_plugin.analysis.branches import (
    CURVES, ViewProblem, branch_gradients, branch_norm_means, render_branches, sample_branch_norms,
)
from exploregs_plugin.analysis.directions import abs_cosine, branch_cosines, nonzero_rows, optical_axis
from exploregs_plugin.analysis.tensorboard import BranchGradientLogger
from exploregs_plugin.cameras import Camera
from exploregs_plugin.analysis.branch_ablation import render_detached
from exploregs_plugin.model.gaussians import render_params
from exploregs_plugin.rasterizer import rasterize_branched
from exploregs_plugin.bench.components.raster_scenes import random_scene

F64 = torch.float64


def _setup(seed: int = 3):
    """Raw float64 parameters of a random scene, a rotated and translated camera, a target."""
    s = random_scene(30, 28, 24, torch.Generator().manual_seed(seed), scale_range=(0.05, 0.25), dtype=F64)
    angle = 0.3
    rot = torch.tensor([[math.cos(angle), 0.0, math.sin(angle)], [0.0, 1.0, 0.0],
                        [-math.sin(angle), 0.0, math.cos(angle)]], dtype=F64)  # fmt: skip
    view = torch.eye(4, dtype=F64)
    view[:3, :3] = rot
    view[:3, 3] = torch.tensor([0.2, -0.1, 0.4], dtype=F64)
    # keep the Gaussians where the identity camera saw them: x_world = R^T (x_cam - t)
    means = (s.means - view[:3, 3]) @ rot
    params = {
        "means": means, "quats": s.quats, "scales": torch.log(s.scales),
        "opacities": torch.logit(s.opacities), "sh0": s.sh_coeffs[:, :1], "shN": s.sh_coeffs[:, 1:],
    }  # fmt: skip
    camera = Camera(view, s.K, s.width, s.height, "probe")
    target = torch.rand(s.height, s.width, 3, generator=torch.Generator().manual_seed(seed + 1), dtype=F64)
    return params, camera, target


def _mse(image, target):
    return ((image - target) ** 2).mean()


def _loss_with_paths(params, camera, target, m2d, mcov, msh):
    sh = torch.cat([params["sh0"], params["shN"]], 1)
    image, *_ = rasterize_branched(m2d, params["quats"], torch.exp(params["scales"]), torch.sigmoid(params["opacities"]), sh,
                          camera, sh_degree=3,
                          means_cov=mcov, means_sh=msh)  # fmt: skip
    return _mse(image, target).item()


def test_each_branch_is_nonzero_and_matches_a_finite_difference_of_its_path_alone():
    params, camera, target = _setup()
    grads = branch_gradients(ViewProblem(params, camera, target, 3, _mse))
    base = params["means"]
    live = torch.nonzero(grads.visible).squeeze(1)
    gen = torch.Generator().manual_seed(7)
    h = 1e-6
    for slot, name in enumerate(("mean2d", "cov", "sh")):
        g = grads.branch(name)
        assert g[live].norm(dim=-1).max() > 0, name
        for i in live[:4].tolist():
            direction = torch.randn(3, generator=gen, dtype=F64)
            vals = []
            for sign in (1.0, -1.0):
                paths = [base, base, base]
                moved = base.clone()
                moved[i] += sign * h * direction
                paths[slot] = moved  # only this path sees the moved mean
                vals.append(_loss_with_paths(params, camera, target, *paths))
            fd = (vals[0] - vals[1]) / (2 * h)
            an = float(g[i] @ direction)
            assert abs(fd - an) <= 1e-6 * max(1.0, abs(fd)) + 1e-9, (name, i, fd, an)
            assert abs(an) > 1e-9, (name, i)


def test_branches_sum_to_the_single_tensor_gradient():
    params, camera, target = _setup()
    grads = branch_gradients(ViewProblem(params, camera, target, 3, _mse))
    means = params["means"].clone().requires_grad_(True)
    image, *_ = render_params({**params, "means": means}, camera, 3, None)
    _mse(image, target).backward()
    assert torch.allclose(grads.mean2d + grads.cov + grads.sh, means.grad, rtol=1e-10, atol=1e-14)
    assert torch.equal(grads.total, grads.mean2d + grads.cov + grads.sh)
    # the screen-space gradient comes with it and is zero for culled Gaussians
    assert grads.means2d_grad.shape == (30, 2)
    assert (grads.means2d_grad[~grads.visible] == 0).all() and grads.means2d_grad.abs().sum() > 0


def test_render_branches_gives_three_separate_leaves_and_leaves_params_alone():
    params, camera, _ = _setup()
    params = {k: v.clone().requires_grad_(True) for k, v in params.items()}
    leaves, image, depth, info = render_branches(params, camera, 3)
    assert len(leaves) == 3 and all(leaf.is_leaf and leaf.requires_grad for leaf in leaves)
    assert len({id(leaf) for leaf in leaves}) == 3
    image.sum().backward()
    assert all(p.grad is None for p in params.values())  # probing never writes into the model
    assert image.shape == (24, 28, 3) and depth.shape == (24, 28, 1)


def test_single_view_mean2d_and_sh_branches_are_orthogonal_to_the_ray():
    params, camera, target = _setup()
    grads = branch_gradients(ViewProblem(params, camera, target, 3, _mse))
    cos = branch_cosines(grads, params["means"], camera)
    assert set(cos) == set(CURVES)
    for name in ("mean2d", "sh"):
        assert cos[name]["ray"].numel() >= 10, name
        assert cos[name]["ray"].max() < 1e-6, (name, float(cos[name]["ray"].max()))
        # ... but not orthogonal to the optical axis (off-centre Gaussians): the ray is the reference
        assert cos[name]["axis"].max() > 1e-2, name
    assert cos["cov"]["ray"].max() > 0.1  # only the covariance branch moves Gaussians in depth
    # manual cosine of one Gaussian
    i = int(torch.nonzero(nonzero_rows(grads.cov, grads.visible))[0])
    ray = params["means"][i] - camera.camera_center
    want = abs(float(grads.cov[i] @ ray)) / float(grads.cov[i].norm() * ray.norm())
    keep = nonzero_rows(grads.cov, grads.visible)
    assert math.isclose(float(cos["cov"]["ray"][keep.cumsum(0)[i] - 1]), want, rel_tol=1e-9)


def test_abs_cosine_and_optical_axis():
    v = torch.tensor([[1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 0.0, 0.0]], dtype=F64)
    r = torch.tensor([[0.0, 0.0, 2.0], [-3.0, 0.0, 0.0], [1.0, 0.0, 0.0]], dtype=F64)
    assert torch.allclose(abs_cosine(v, r), torch.tensor([0.0, 1 / math.sqrt(2), 0.0], dtype=F64))
    _, camera, _ = _setup()
    axis = optical_axis(camera)
    # the optical axis maps to camera +z
    assert torch.allclose(camera.viewmat[:3, :3] @ axis, torch.tensor([0.0, 0.0, 1.0], dtype=F64), atol=1e-12)


def test_norm_means_and_view_average():
    params, camera, target = _setup()
    grads = branch_gradients(ViewProblem(params, camera, target, 3, _mse))
    means = branch_norm_means(grads)
    live = grads.visible
    for name in CURVES:
        assert math.isclose(means[name], float(grads.branch(name)[live].norm(dim=-1).mean()), rel_tol=1e-12)
    assert means["mean2d"] > 0 and means["cov"] > 0 and means["sh"] > 0
    params2, camera2, target2 = _setup(seed=9)
    # both views see the same Gaussians: the average is the mean of the two per-view values
    other = branch_norm_means(branch_gradients(ViewProblem(params, camera2, target2, 3, _mse)))
    avg = sample_branch_norms([ViewProblem(params, camera, target, 3, _mse), ViewProblem(params, camera2, target2, 3, _mse)])
    for name in CURVES:
        assert math.isclose(avg[name], (means[name] + other[name]) / 2, rel_tol=1e-12)


class _Sink:
    def __init__(self):
        self.logged: list[tuple[str, float, int]] = []

    def scalar(self, tag, value, step):
        self.logged.append((tag, value, step))


def test_training_logger_logs_at_its_interval_and_leaves_training_untouched(tiny_dm):
    from exploregs_plugin.engine.pipeline import PipelineConfig
    from exploregs_plugin.schedule import ScheduleConfig

    schedule = ScheduleConfig().resolve(20)
    pipeline = PipelineConfig(datamanager=tiny_dm.config).setup(schedule, seed=0)
    before = {k: v.detach().clone() for k, v in pipeline.params.items()}
    order = pipeline.datamanager.state_dict()
    rng = pipeline.generator.get_state()
    sink = _Sink()
    hook = BranchGradientLogger(every=5, views=2)
    assert hook(pipeline, 3, sink) is None and sink.logged == []
    values = hook(pipeline, 5, sink)
    tags = {t for t, _, _ in sink.logged}
    assert {f"grad_branches/{n}" for n in CURVES} <= tags
    assert all(step == 5 for _, _, step in sink.logged)
    assert values["mean2d"] > values["cov"] > 0 and math.isfinite(values["total"])
    for k, v in pipeline.params.items():
        assert torch.equal(v.detach(), before[k]) and v.grad is None
    assert torch.equal(pipeline.generator.get_state(), rng)
    assert str(pipeline.datamanager.state_dict()) == str(order)
    assert BranchGradientLogger(every=0)(pipeline, 5, sink) is None


def test_view_problem_rejects_a_target_of_the_wrong_size():
    params, camera, target = _setup()
    import pytest

    with pytest.raises(ValueError, match="target image has shape"):
        ViewProblem(params, camera, target[:-1], 3, _mse)


def test_switching_off_the_2d_mean_branch_keeps_the_densification_statistic():
    """Detaching the 2D-mean path removes its share of the position gradient, but the projected
    means keep the same screen-space gradient (ADC's statistic), so the ablated run still
    densifies."""
    params, camera, target = _setup()
    leaves = {k: v.clone().requires_grad_(True) for k, v in params.items()}
    # the torch reference on both sides: a detached path makes the compiled backend use the torch
    # projection too, and two code paths agree to rounding, not bit for bit
    reference = RasterSettings(backend="torch")
    image, _, _, info = render_params(leaves, camera, 3, None, settings=reference)
    info["means2d"].retain_grad()
    _mse(image, target).backward()
    full_means, full_2d = leaves["means"].grad.clone(), info["means2d"].grad.clone()

    grads = branch_gradients(ViewProblem(params, camera, target, 3, _mse))
    ablated = {k: v.clone().requires_grad_(True) for k, v in params.items()}
    image2, _, _, info2 = render_detached(ablated, camera, 3, None, ("mean2d",), settings=reference)
    assert info2["means2d"].requires_grad
    info2["means2d"].retain_grad()
    _mse(image2, target).backward()
    torch.testing.assert_close(image2, image, rtol=0, atol=0)
    torch.testing.assert_close(info2["means2d"].grad, full_2d, rtol=1e-12, atol=1e-15)
    assert float(full_2d.norm()) > 0
    # What reaches the mean is the total less the 2D-mean branch.
    torch.testing.assert_close(ablated["means"].grad, full_means - grads.mean2d, rtol=1e-9, atol=1e-12)
    assert float(grads.mean2d.norm()) > 0


def test_the_branch_ablation_method_renders_through_its_detached_paths():
    from exploregs_plugin.analysis.branch_ablation import BranchAblationModel, BranchAblationModelConfig
    from exploregs_plugin.method_configs import get_method

    assert isinstance(get_method("exploregs-branch-ablation").config.pipeline.model, BranchAblationModelConfig)
    g = torch.Generator().manual_seed(0)
    points, rgb = torch.randn(30, 3, generator=g) * 0.3, torch.rand(30, 3, generator=g)
    camera = Camera(torch.eye(4), torch.tensor([[40.0, 0, 16], [0, 40.0, 16], [0, 0, 1]]), 32, 32)
    camera.viewmat[2, 3] = 3.0
    grads = {}
    for paths in ((), ("cov",), ("mean2d", "cov", "sh")):
        model = BranchAblationModelConfig(detach_paths=paths).setup(points, rgb)
        assert isinstance(model, BranchAblationModel)
        image, *_ = model.render(camera, 3)
        image.square().sum().backward()
        grads[paths] = model.params["means"].grad
    # every path off: nothing reaches the means; one path off: a different, non-zero gradient
    assert grads[("mean2d", "cov", "sh")] is None
    assert float(grads[("cov",)].norm()) > 0 and not torch.allclose(grads[("cov",)], grads[()])
    with pytest.raises(ValueError, match="unknown position paths"):
        BranchAblationModelConfig(detach_paths=("depth",)).setup(points, rgb)
