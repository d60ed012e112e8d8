"""The deformation field of dynamic scenes: shapes, gradients, time continuity, the model's hooks."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch

from exploregs_plugin.cameras import Camera
from exploregs_plugin.model.deformation import (PLANE_PAIRS, SPACE_PLANES, TIME_PLANES, DeformationField,
                                                HexPlaneField, hexplane_features, plane_tv, robust_box,
                                                sample_plane, static_l1, time_smoothness)
from exploregs_plugin.model.dynamic import DeformationConfig, DynamicGaussianModelConfig, deform_params
from exploregs_plugin.model.optim import exponential_lr


def tiny_field(dtype: torch.dtype = torch.float64, seed: int = 0) -> DeformationField:
    field = DeformationField(torch.tensor([-1.0, -1.0, -1.0]), torch.tensor([1.0, 1.0, 1.0]), (3, 4, 3, 5), (1, 2),
                             2, 5, 2, torch.Generator().manual_seed(seed)).to(dtype)
    # the heads start at zero (identity deformation); give them values so every path carries gradient
    with torch.no_grad():
        for p in field.decoder.parameters():
            p.copy_(torch.randn(p.shape, generator=torch.Generator().manual_seed(seed + p.numel()), dtype=dtype) * 0.5)
        gen = torch.Generator().manual_seed(seed + 7)
        for level in field.grid.levels:
            for plane in level:  # values near 1, so that every plane (time included) matters
                plane.copy_(1.0 + 0.5 * torch.randn(plane.shape, generator=gen, dtype=dtype))
    return field


def test_plane_layout_and_init():
    assert len(PLANE_PAIRS) == 6 and set(SPACE_PLANES) | set(TIME_PLANES) == set(range(6))
    assert all(3 not in PLANE_PAIRS[i] for i in SPACE_PLANES) and all(3 in PLANE_PAIRS[i] for i in TIME_PLANES)
    grid = HexPlaneField((4, 5, 6, 7), (1, 2), 3, torch.Generator().manual_seed(0))
    for level, factor in zip(grid.levels, (1, 2)):
        res = (4 * factor, 5 * factor, 6 * factor, 7)
        for index, (plane, (a, b)) in enumerate(zip(level, PLANE_PAIRS)):
            assert plane.shape == (3, res[b], res[a])  # rows: the second coordinate
            if index in TIME_PLANES:
                assert torch.equal(plane, torch.ones_like(plane))  # no motion at the start
            else:
                assert 0.1 <= float(plane.detach().min()) and float(plane.detach().max()) <= 0.5
    # time planes at 1: the features do not depend on time at the start
    q = torch.rand(50, 4) * 2 - 1
    q2 = q.clone()
    q2[:, 3] = -q[:, 3]
    assert torch.allclose(grid(q), grid(q2), rtol=1e-6, atol=0)
    assert grid(q).shape == (50, 6)


def test_sample_plane_is_exact_at_nodes_and_bilinear_between():
    plane = torch.arange(12, dtype=torch.float64).reshape(1, 3, 4)  # rows = 3 (b), columns = 4 (a)
    # node (column 2, row 1) sits at a = -1 + 2 * 2 / 3, b = 0
    node = torch.tensor([[-1 + 4 / 3, 0.0]], dtype=torch.float64)
    assert float(sample_plane(plane, node)) == pytest.approx(float(plane[0, 1, 2]))
    # halfway between columns 0 and 1 of row 0: the mean of the two
    mid = torch.tensor([[-1 + 1 / 3, -1.0]], dtype=torch.float64)
    assert float(sample_plane(plane, mid)) == pytest.approx(0.5 * float(plane[0, 0, 0] + plane[0, 0, 1]))
    # outside [-1, 1]: the border value
    far = torch.tensor([[5.0, -7.0]], dtype=torch.float64)
    assert float(sample_plane(plane, far)) == pytest.approx(float(plane[0, 0, 3]))


def test_hexplane_features_are_the_product_of_the_six_planes():
    gen = torch.Generator().manual_seed(1)
    res = (3, 4, 5, 6)
    planes = [torch.rand(2, res[b], res[a], generator=gen, dtype=torch.float64) for a, b in PLANE_PAIRS]
    q = torch.rand(7, 4, generator=gen, dtype=torch.float64) * 2 - 1
    expected = torch.ones(7, 2, dtype=torch.float64)
    for plane, (a, b) in zip(planes, PLANE_PAIRS):
        expected = expected * sample_plane(plane, q[:, [a, b]])
    assert torch.allclose(hexplane_features([planes, planes], q), torch.cat([expected, expected], dim=1))


def test_field_shapes_and_identity_at_start():
    field = DeformationField(torch.zeros(3), torch.ones(3), (4, 4, 4, 3), (1,), 4, 8, 1, torch.Generator().manual_seed(0))
    means = torch.rand(20, 3)
    dx, dq, ds = field(means, 0.4)
    assert dx.shape == (20, 3) and dq.shape == (20, 4) and ds.shape == (20, 3)
    assert torch.equal(dx, torch.zeros_like(dx)) and torch.equal(dq, torch.zeros_like(dq))  # zero-initialised heads
    assert not bool(field.active)


def test_field_gradients_match_finite_differences():
    field = tiny_field()
    means = (torch.rand(6, 3, generator=torch.Generator().manual_seed(3), dtype=torch.float64) * 1.6 - 0.8)
    means.requires_grad_(True)
    params = [means] + list(field.parameters())

    def fn(m, *_):
        dx, dq, ds = field(m, 0.37)
        return torch.cat([dx, dq, ds], dim=1)

    # fast mode compares the analytical and the numerical Jacobian through random vectors on both
    # sides (u^T J v), which a wrong entry anywhere moves: the same check of every input's gradient,
    # without the 2 x 850 evaluations of the whole numerical Jacobian (4.3 s of CPU; 0.15 s)
    assert torch.autograd.gradcheck(fn, params, eps=1e-6, atol=1e-5, rtol=1e-4, fast_mode=True)


def test_field_offsets_are_continuous_in_time():
    """Offsets are continuous in time: piecewise multilinear, so a step dt changes them by O(dt)."""
    field = tiny_field()
    means = torch.rand(10, 3, generator=torch.Generator().manual_seed(4), dtype=torch.float64) * 1.6 - 0.8
    ts = torch.linspace(0.0, 1.0, 2001, dtype=torch.float64)
    with torch.no_grad():
        # the 2001 times in one batch of rows (the field's forward, its coordinates taken at each
        # time): every operator works row by row, and one call costs what 2001 calls cost in overhead
        q = torch.cat([field.normalized_coords(means, float(t)) for t in ts])
        values = torch.cat(field.decoder(field.grid(q)), dim=1).reshape(len(ts), len(means), 10)  # [T, N, 10]
        for i in (0, 737, 2000):  # the batch is what the field gives at each time
            assert torch.allclose(values[i], torch.cat(field(means, float(ts[i])), dim=1), rtol=1e-12, atol=1e-14)
    steps = (values[1:] - values[:-1]).abs().amax(dim=(1, 2))
    assert float(steps.max()) < 50 * float(steps.median()) + 1e-9  # no jump anywhere
    assert float(steps.max()) < 0.05 * float((values.amax(0) - values.amin(0)).max())
    # the offsets do change over the clip (the time planes were perturbed)
    assert float((values[-1] - values[0]).abs().max()) > 1e-3


@pytest.mark.parametrize("time", [0.0, 0.5, 1.0])
def test_halving_the_time_step_halves_the_change(time):
    """Lipschitz in time, not merely small, at the clip's start, middle and end."""
    field = tiny_field()
    means = torch.rand(10, 3, generator=torch.Generator().manual_seed(4), dtype=torch.float64) * 1.6 - 0.8
    t0 = min(time, 0.99)
    with torch.no_grad():
        a = torch.cat(field(means, t0), 1)
        d1 = (torch.cat(field(means, t0 + 1e-3), 1) - a).abs().max()
        d2 = (torch.cat(field(means, t0 + 5e-4), 1) - a).abs().max()
    assert float(d2) == pytest.approx(0.5 * float(d1), rel=1e-2, abs=1e-12)


def test_regularisers():
    flat = torch.ones(2, 5, 6)
    assert float(plane_tv(flat)) == 0.0 and float(static_l1(flat)) == 0.0 and float(time_smoothness(flat)) == 0.0
    ramp = torch.arange(5.0).reshape(1, 5, 1).expand(1, 5, 3).contiguous()  # linear in time (rows)
    assert float(time_smoothness(ramp)) == pytest.approx(0.0)  # constant velocity costs nothing
    assert float(plane_tv(ramp)) == pytest.approx(1.0)  # unit steps along the rows, none along columns
    bump = torch.zeros(1, 5, 1)
    bump[0, 2, 0] = 1.0
    assert float(time_smoothness(bump)) == pytest.approx((1 + 4 + 1) / 3)
    assert float(static_l1(torch.zeros(1, 2, 2))) == 1.0


def test_robust_box_ignores_stray_points():
    points = torch.cat([torch.rand(1000, 3), torch.tensor([[500.0, -300.0, 900.0]])])
    low, high = robust_box(points, 1.0, 0.1)
    assert float(high.max()) < 2.0 and float(low.min()) > -1.0
    with pytest.raises(ValueError, match="needs points"):
        robust_box(torch.zeros(0, 3), 1.0, 0.1)


def test_exponential_lr():
    assert exponential_lr(1e-3, 1e-5, 0.0) == pytest.approx(1e-3)
    assert exponential_lr(1e-3, 1e-5, 1.0) == pytest.approx(1e-5)
    assert exponential_lr(1e-3, 1e-5, 0.5) == pytest.approx(1e-4)
    assert exponential_lr(1e-3, 1e-5, 7.0) == pytest.approx(1e-5)  # clamped
    assert exponential_lr(0.0, 1e-5, 0.5) == 0.0


def _camera(time: float | None = None) -> Camera:
    viewmat = torch.eye(4)
    viewmat[2, 3] = 3.0
    K = torch.tensor([[40.0, 0.0, 16.0], [0.0, 40.0, 12.0], [0.0, 0.0, 1.0]])
    return Camera(viewmat, K, 32, 24, "c", time)


def _model(start_frac: float = 0.0):
    points = torch.rand(64, 3, generator=torch.Generator().manual_seed(0)) - 0.5
    config = DynamicGaussianModelConfig(sh_degree=0, deformation=DeformationConfig(
        resolution=(4, 4, 4, 3), multires=(1,), features=4, width=8, start_frac=start_frac))
    return config.setup(points, None)


def test_model_warm_up_then_deformation():
    model = _model(start_frac=0.5)
    assert model.params_at(0.3) is model.params  # warm-up: the canonical Gaussians
    assert model.regularization_loss() is None
    model.begin_step(4, 10)
    assert not bool(model.deformation.active)
    before = model.render(_camera(0.3))[0]
    model.begin_step(5, 10)
    assert bool(model.deformation.active)
    # zero-initialised heads: switching the deformation on does not change the image
    assert torch.allclose(model.render(_camera(0.3))[0], before, atol=1e-6)
    assert float(model.regularization_loss().detach()) >= 0.0
    assert [name for name, _ in model.part_parameters()][0].startswith("deformation.")
    assert set(model.parts) == {"deformation"} and model.parts["deformation"] is model.deformation
    # the field's two groups cover every trained tensor of the part, once
    groups = model.part_param_groups(1.0, 10)
    assert [g.name for g in groups] == ["grid", "mlp"]
    assert sorted(id(p) for g in groups for p in g.params) == sorted(id(p) for _, p in model.part_parameters())


def test_render_uses_deformed_means_and_their_screen_gradient():
    """The projected 2D means are the deformed ones: densification reads their gradient."""
    model = _model()
    model.begin_step(0, 10)
    with torch.no_grad():
        model.deformation.decoder.position[-1].bias.copy_(torch.tensor([0.05, -0.02, 0.0]))
    camera = _camera(0.6)
    image, _, _, info = model.render(camera)
    deformed = deform_params(model.params, model.deformation, 0.6)["means"]
    assert torch.allclose(deformed, model.params["means"] + torch.tensor([0.05, -0.02, 0.0]), atol=1e-6)
    cam = deformed.detach() @ camera.viewmat[:3, :3].T + camera.viewmat[:3, 3]
    uv = cam[:, :2] / cam[:, 2:3] * 40.0 + torch.tensor([16.0, 12.0])
    visible = info["radii"].reshape(len(uv), -1)[:, 0] > 0
    assert torch.allclose(info["means2d"].detach()[visible], uv[visible], atol=1e-3)
    info["means2d"].retain_grad()
    image.sum().backward()
    assert info["means2d"].grad is not None and float(info["means2d"].grad.abs().sum()) > 0
    # the canonical means and the field both receive gradient through the deformed means
    assert model.params["means"].grad is not None
    assert model.deformation.decoder.position[-1].bias.grad is not None


def test_time_of_a_static_camera_is_the_first_frame():
    model = _model()
    model.begin_step(0, 10)
    with torch.no_grad():
        model.deformation.decoder.position[-1].weight.normal_(0, 0.5)
        for level in model.deformation.grid.levels:
            for i in TIME_PLANES:
                level[i].normal_(1.0, 0.3)
    assert torch.equal(model.params_at(None)["means"], model.params_at(0.0)["means"])
    assert not torch.equal(model.params_at(1.0)["means"], model.params_at(0.0)["means"])


def test_config_checks():
    with pytest.raises(ValueError, match="start_frac"):
        DynamicGaussianModelConfig(deformation=DeformationConfig(start_frac=1.5)).setup(torch.rand(8, 3), None)
    with pytest.raises(ValueError, match="resolution"):
        HexPlaneField((4, 4, 1, 4), (1,), 2)
    assert math.isclose(replace(DeformationConfig(), box_margin=0.0).box_margin, 0.0)
