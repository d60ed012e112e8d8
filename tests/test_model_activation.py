"""The one activation from raw parameters to what the rasterizers take, and its detached view."""

from __future__ import annotations

import torch

from exploregs_plugin.model.gaussians import activate, activate_detached


def _raw(n: int = 5, k: int = 4) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(3)
    shapes = {"means": (n, 3), "quats": (n, 4), "scales": (n, 3), "opacities": (n,), "sh0": (n, 1, 3), "shN": (n, k - 1, 3)}
    return {name: (4 * torch.randn(shape, generator=g)).requires_grad_(True) for name, shape in shapes.items()}


def test_activate_applies_exp_sigmoid_and_stacks_the_sh_bands_in_the_graph():
    raw = _raw()
    means, quats, scales, opacities, sh = activate(raw)
    assert means is raw["means"] and quats is raw["quats"]
    torch.testing.assert_close(scales, raw["scales"].detach().exp(), rtol=0, atol=0)
    torch.testing.assert_close(opacities, 1 / (1 + torch.exp(-raw["opacities"].detach())), rtol=1e-6, atol=1e-7)
    assert sh.shape == (5, 4, 3)
    assert torch.equal(sh[:, :1], raw["sh0"].detach()) and torch.equal(sh[:, 1:], raw["shN"].detach())
    # d exp(s)/ds = exp(s), d sigmoid(o)/do = o'(1 - o'), d sh/d sh0 = 1: the chain rule reaches the raw tensors
    (scales.sum() + opacities.sum() + sh.sum()).backward()
    torch.testing.assert_close(raw["scales"].grad, scales.detach())
    torch.testing.assert_close(raw["opacities"].grad, (opacities * (1 - opacities)).detach())
    assert torch.equal(raw["sh0"].grad, torch.ones_like(raw["sh0"]))
    assert torch.equal(raw["shN"].grad, torch.ones_like(raw["shN"]))


def test_activate_detached_is_the_same_values_cut_from_the_graph():
    raw = _raw()
    live, cut = activate(raw), activate_detached(raw)
    for a, b in zip(live, cut):
        assert torch.equal(a.detach(), b)
        assert not b.requires_grad and b.grad_fn is None
