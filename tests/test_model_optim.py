"""The run's Adam: fused where the device has it, and the same Adam as torch's for-loop one up to
float32 rounding (exploregs_plugin/model/optim.py)."""

from __future__ import annotations

import torch
from torch import nn

from exploregs_plugin.model.optim import ADAM_EPS, OptimizerConfig, OptimizerSet, ParamGroup, adam


def _gradients(step: int, shape: tuple[int, ...]) -> torch.Tensor:
    """Gradients over twelve orders of magnitude, with rows that never get one (Gaussians that no
    view sees: their moments stay zero, and m / (sqrt(v) + eps) must stay 0, not 0/0)."""
    g = torch.Generator().manual_seed(1000 + step)
    grad = torch.randn(shape, generator=g) * torch.logspace(-9, 3, shape[0])[:, None]
    grad[::7] = 0.0
    return grad


def test_fused_adam_follows_the_for_loop_adam_over_100_steps():
    torch.manual_seed(0)
    start = torch.randn(64, 3)
    fused_p, loop_p = nn.Parameter(start.clone()), nn.Parameter(start.clone())
    fused = adam([{"params": [fused_p], "lr": 1e-2}], (0.9, 0.999))
    loop = torch.optim.Adam([loop_p], lr=1e-2, eps=ADAM_EPS, betas=(0.9, 0.999), foreach=False)
    assert fused.defaults["fused"] and not loop.defaults["fused"]
    for step in range(100):
        lr = 1e-2 * 0.97 ** step  # the means' decaying rate, set each step as the trainer does
        for opt, p in ((fused, fused_p), (loop, loop_p)):
            opt.param_groups[0]["lr"] = lr
            p.grad = _gradients(step, tuple(start.shape))
            opt.step()
    moved = (loop_p - start).abs()
    assert torch.equal(fused_p.detach()[::7], start[::7]) and torch.equal(loop_p.detach()[::7], start[::7])
    assert (moved[1:7] > 1e-4).all()  # every row with a gradient moved, the 1e-9 ones too (eps 1e-15)
    # float32 rounding of 100 steps of a few ops each, on moves of order 1
    assert torch.allclose(fused_p.detach(), loop_p.detach(), rtol=0.0, atol=2e-6), (fused_p - loop_p).abs().max()
    for key in ("exp_avg", "exp_avg_sq"):
        a, b = fused.state[fused_p][key], loop.state[loop_p][key]
        assert torch.allclose(a, b, rtol=1e-5, atol=0.0), (key, ((a - b).abs() / b.abs().clamp_min(1e-30)).max())


def test_the_runs_optimizers_are_fused_on_the_cpu_and_keep_their_rates():
    params = nn.ParameterDict({name: nn.Parameter(torch.zeros(5, k)) for name, k in
                               (("means", 3), ("scales", 3), ("quats", 4), ("opacities", 1), ("sh0", 3), ("shN", 45))})
    config = OptimizerConfig()
    optimizers = config.setup(params, scene_extent=2.0, batch_size=4)
    assert all(opt.defaults["fused"] for opt in optimizers.values())
    assert optimizers["means"].param_groups[0]["lr"] == config.means_lr * 2.0 * 2.0  # extent x sqrt(B)
    assert optimizers["means"].defaults["betas"] == (0.9 ** 4, 0.999 ** 4)
    field = ParamGroup("planes", [nn.Parameter(torch.zeros(3))], lambda step: 1e-3 / (1 + step))
    optimizer_set = OptimizerSet(optimizers, lambda step: 0.5 ** step, [field])
    assert optimizer_set.shared.defaults["fused"]
    for p in list(params.values()) + field.params:
        p.grad = torch.ones_like(p)
    assert optimizer_set.step(3) == 0.125 and optimizer_set.lrs()["planes"] == 1e-3 / 4
    # Adam's first step moves every element by lr (m / sqrt(v) = 1): the fused step did step
    assert torch.allclose(params["means"].detach(), torch.full((5, 3), -0.125))
