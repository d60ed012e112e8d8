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
from typing import TYPE_CHECKING, Literal

import torch
from torch import Tensor

from ..rasterizer.projection import covariances_3d
from .errors import StrategyError
from .operator_contract import Operator
from .row_ops import num_gaussians

if TYPE_CHECKING:
    from .base import StepContext
    from .default import DefaultStrategy

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
class PositionNoise(Operator):
    """3DGS-MCMC's position noise after every optimizer step, isotropic or along the ray. An
    operator of the ray strategy, and the noise of MCMC (which calls :meth:`perturb` itself)."""

    COUNTS = ("perturbed",)

    mode: NoiseMode = "isotropic"
    """'isotropic' (3DGS-MCMC) or 'ray': projected onto the ray from the step's first training
    camera to the Gaussian, so only depth is explored."""
    lr: float = 5e5
    """Noise scale relative to the means learning rate (3DGS-MCMC: 5e5)."""
    gate_k: float = 100.0
    """Steepness k of the opacity gate sigmoid(-k (o - t))."""
    gate_t: float = 0.005
    """Opacity t at which the gate is one half."""

    def __post_init__(self) -> None:
        if self.mode not in ("isotropic", "ray"):
            raise StrategyError(f"noise mode must be 'isotropic' or 'ray', got '{self.mode}'")
        # lr = 0 switches the noise off; a negative or non-finite scale, a gate that does not fall
        # with opacity (k <= 0) or a threshold outside the opacities' range is a mistake
        if not (math.isfinite(self.lr) and self.lr >= 0.0):
            raise StrategyError(f"noise lr must be finite and >= 0, got {self.lr}")
        if not (math.isfinite(self.gate_k) and self.gate_k > 0.0):
            raise StrategyError(f"noise gate_k must be finite and > 0, got {self.gate_k}")
        if not 0.0 <= self.gate_t <= 1.0:
            raise StrategyError(f"noise gate_t must be an opacity in [0, 1], got {self.gate_t}")

    def explore(self, owner: DefaultStrategy, ctx: StepContext) -> dict[str, int]:
        return {"perturbed": self.perturb(ctx, type(owner).__name__)}

    def perturb(self, ctx: StepContext, who: str) -> int:
        """Add the noise to ``params['means']`` in place; returns how many Gaussians moved."""
        params, lr = ctx.params, ctx.lr
        if num_gaussians(params) == 0:
            return 0
        if not (math.isfinite(lr) and lr > 0.0):
            raise StrategyError(
                f"{who} scales its noise by the means learning rate: pass "
                f"lr=<current means lr> (> 0) to step_post_backward, got {lr}"
            )
        eta = position_noise(
            params["means"],
            params["quats"],
            params["scales"],
            params["opacities"],
            self.lr * lr,
            ctx.rng("position noise"),
            mode=self.mode,
            # a step of several views perturbs along the rays of its first view
            camera_center=ctx.views[0].camera_center,
            gate_k=self.gate_k,
            gate_t=self.gate_t,
        )
        # A non-finite row (degenerate parameters) must not spread NaN into the means.
        eta = torch.where(torch.isfinite(eta), eta, torch.zeros_like(eta))
        with torch.no_grad():
            params["means"].add_(eta.to(params["means"].dtype))
        return num_gaussians(params)
