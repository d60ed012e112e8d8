"""Positional noise of 3DGS-MCMC, isotropic or constrained to the viewing ray.

    eta = noise_lr * lr * sigmoid(-k (o - t)) * Sigma z,    z ~ N(0, I)

with the means learning rate ``lr``, k = 100 and t = 0.005, so opaque Gaussians barely move and
the noise follows the Gaussian's own covariance Sigma. In 'ray' mode eta is projected onto the
unit ray d from the current training camera centre to the Gaussian, (eta . d) d, so only depth is
explored. The noise is applied after each optimizer step.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import torch
from torch import Tensor

from .base import StepContext, Strategy, StrategyError
from .default import DefaultStrategy
from ..rasterizer.projection import covariances_3d
from .ops import num_gaussians

NoiseMode = Literal["isotropic", "ray"]

_EPS = 1e-12


def position_noise(
    means: Tensor,
    quats: Tensor,
    log_scales: Tensor,
    opacity_logits: Tensor,
    scale: float,
    generator: torch.Generator,
    *,
    mode: str = "isotropic",
    camera_center: Tensor | None = None,
    gate_k: float = 100.0,
    gate_t: float = 0.005,
) -> Tensor:
    """The noise vector eta for every Gaussian: [N, 3] in the dtype of ``means``.

    means [N, 3], quats [N, 4], log_scales [N, 3], opacity_logits [N]; ``scale`` is
    noise_lr x lr. In 'ray' mode ``camera_center`` [3] is required; a Gaussian at the camera
    centre (no ray direction) gets no noise.
    """
    n = means.shape[0]
    dtype = means.dtype
    z = torch.randn(n, 3, generator=generator, dtype=dtype, device=generator.device).to(means.device)
    gate = torch.sigmoid(-gate_k * (torch.sigmoid(opacity_logits.detach().to(dtype)) - gate_t))
    sigma = covariances_3d(quats.detach().to(dtype), torch.exp(log_scales.detach().to(dtype)))
    eta = torch.einsum("nij,nj->ni", sigma, z * (gate * scale).unsqueeze(-1))
    if mode == "isotropic":
        return eta
    if mode != "ray":
        raise StrategyError(f"noise mode must be 'isotropic' or 'ray', got '{mode}'")
    if camera_center is None:
        raise StrategyError("ray noise needs camera_center (the current training camera centre)")
    ray = means.detach().to(dtype) - camera_center.to(dtype=dtype, device=means.device).reshape(1, 3)
    length = ray.norm(dim=-1, keepdim=True)
    direction = torch.where(length > _EPS, ray / length.clamp_min(_EPS), torch.zeros_like(ray))
    return (eta * direction).sum(dim=-1, keepdim=True) * direction


@dataclass
class NoiseMixin(Strategy):
    """Fields and the update shared by every strategy that perturbs positions."""

    noise_lr: float = 5e5
    """Noise scale relative to the means learning rate (3DGS-MCMC: 5e5)."""
    noise_gate_k: float = 100.0
    """Steepness k of the opacity gate sigmoid(-k (o - t))."""
    noise_gate_t: float = 0.005
    """Opacity t at which the gate is one half."""

    def perturb_positions(self, ctx: StepContext, mode: str) -> int:
        """Add the noise to ``params['means']`` in place; returns how many Gaussians moved."""
        params, lr = ctx.params, ctx.lr
        if num_gaussians(params) == 0:
            return 0
        if not (math.isfinite(lr) and lr > 0.0):
            raise StrategyError(
                f"{type(self).__name__} scales its noise by the means learning rate: pass "
                f"lr=<current means lr> (> 0) to step_post_backward, got {lr}"
            )
        eta = position_noise(
            params["means"],
            params["quats"],
            params["scales"],
            params["opacities"],
            self.noise_lr * lr,
            ctx.rng("position noise"),
            mode=mode,
            # a step of several views perturbs along the rays of its first view
            camera_center=ctx.views[0].camera_center,
            gate_k=self.noise_gate_k,
            gate_t=self.noise_gate_t,
        )
        # A non-finite row (degenerate parameters) must not spread NaN into the means.
        eta = torch.where(torch.isfinite(eta), eta, torch.zeros_like(eta))
        with torch.no_grad():
            params["means"].add_(eta.to(params["means"].dtype))
        return num_gaussians(params)


@dataclass
class RayPerturbationMixin(NoiseMixin, DefaultStrategy):
    """Ray-constrained perturbation after every optimizer step; compose it in front of Default."""

    def explore(self, ctx: StepContext) -> dict[str, int]:
        counts = super().explore(ctx)
        counts["perturbed"] = self.perturb_positions(ctx, "ray")
        return counts
