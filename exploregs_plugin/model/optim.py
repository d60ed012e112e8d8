"""Adam optimizers with the 3DGS learning rates: one per Gaussian parameter name, and the run's
optimizer set (:class:`OptimizerSet`) that adds a model's other parameter groups."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch
from torch import nn

from exploregs_plugin.model.fused_adam import FUSED_DEVICES, FusedAdam, fused_adam_step
from exploregs_plugin.rasterizer.composite import single_threaded_ops

ADAM_EPS = 1e-15  # 3DGS uses a tiny epsilon: Adam steps stay near lr even for tiny gradients
ADAM_BETAS = (0.9, 0.999)

Optimizer = FusedAdam | torch.optim.Adam


def adam(groups: list[dict[str, Any]], betas: tuple[float, float]) -> Optimizer:
    """Adam with the 3DGS epsilon: torch's fused kernel where the parameters' device has it
    (:class:`FusedAdam`), else torch's Adam.

    The fused kernel reads and writes each element once, where the for-loop Adam makes a temporary
    per operation (30,000 Gaussians: 1.35 ms against 7.73 ms a step on two CPU threads). It rounds
    differently from the for-loop Adam (both are float32 Adam: tests/test_model_optim.py). On the
    CPU it runs on one thread (:meth:`OptimizerSet.step`)."""
    devices = {p.device.type for group in groups for p in group["params"]}
    if devices <= set(FUSED_DEVICES):
        return FusedAdam(groups, eps=ADAM_EPS, betas=betas)
    return torch.optim.Adam(groups, eps=ADAM_EPS, betas=betas)


def batch_lr_scale(batch_size: int, rule: bool = True) -> float:
    """Learning-rate factor for B views per step: sqrt(B) under the batch rule, else 1.

    Grendel (Zhao et al. 2025) keeps a run's trajectory close to the B = 1 run by scaling every
    learning rate by sqrt(B) (the mean gradient of B views has about 1/sqrt(B) of one view's
    noise) and raising Adam's betas to the power B (the moments then forget at the same rate per
    image seen)."""
    return math.sqrt(batch_size) if rule else 1.0


def batch_betas(batch_size: int, rule: bool = True) -> tuple[float, float]:
    """Adam's (beta1, beta2) for B views per step: (0.9^B, 0.999^B) under the batch rule."""
    if not rule:
        return ADAM_BETAS
    return (ADAM_BETAS[0] ** batch_size, ADAM_BETAS[1] ** batch_size)


@dataclass
class OptimizerConfig:
    """3DGS learning rates (Kerbl et al. 2023 reference values)."""

    means_lr: float = 1.6e-4
    """Initial position learning rate, multiplied by the scene extent."""
    means_lr_final: float = 1.6e-6
    """Final position learning rate (x scene extent), reached by exponential decay at the last step."""
    scales_lr: float = 5e-3
    """Learning rate of the log-scales."""
    quats_lr: float = 1e-3
    """Learning rate of the rotation quaternions."""
    opacities_lr: float = 5e-2
    """Learning rate of the opacity logits."""
    sh0_lr: float = 2.5e-3
    """Learning rate of the SH DC (base colour) term."""
    shN_lr: float = 2.5e-3 / 20.0
    """Learning rate of the higher-order SH: 20x below the DC term's, as in 3DGS."""

    def __post_init__(self) -> None:
        # Checked when the config is built, so a bad rate is one line before any work (a NaN rate
        # otherwise surfaces as a non-finite parameter at step 0, a negative one trains uphill).
        for name in ("means_lr", "means_lr_final", "scales_lr", "quats_lr", "opacities_lr", "sh0_lr", "shN_lr"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value >= 0):
                raise ValueError(f"{type(self).__name__}.{name} must be a finite learning rate >= 0 "
                                 f"(0 freezes the parameter), got {value}")

    def base_lrs(self, scene_extent: float) -> dict[str, float]:
        return {
            "means": self.means_lr * scene_extent,
            "scales": self.scales_lr,
            "quats": self.quats_lr,
            "opacities": self.opacities_lr,
            "sh0": self.sh0_lr,
            "shN": self.shN_lr,
        }

    def setup(self, params: nn.ParameterDict, scene_extent: float, batch_size: int = 1,
              batch_rule: bool = True) -> dict[str, Optimizer]:
        """One Adam per parameter name (so ops can resize one tensor and its moments at a time),
        with the learning rates and betas of :func:`batch_lr_scale` / :func:`batch_betas`."""
        scale = batch_lr_scale(batch_size, batch_rule)
        lrs = {name: lr * scale for name, lr in self.base_lrs(scene_extent).items()}
        betas = batch_betas(batch_size, batch_rule)
        return {name: adam([{"params": [params[name]], "lr": lrs[name], "name": name}], betas) for name in params.keys()}

    def means_lr_at(self, step: int, max_steps: int, scene_extent: float) -> float:
        """Exponential decay lr(t) = lr0 (lr1 / lr0)^(t / max_steps), both scaled by the extent."""
        progress = min(max(step, 0), max_steps) / max(max_steps, 1)
        return exponential_lr(self.means_lr * scene_extent, self.means_lr_final * scene_extent, progress)


def exponential_lr(lr0: float, lr1: float, progress: float) -> float:
    """lr0 (lr1 / lr0)^p for a progress p clamped to [0, 1]; lr0 when either rate is not positive."""
    p = min(max(progress, 0.0), 1.0)
    if lr0 <= 0.0 or lr1 <= 0.0:
        return lr0
    return lr0 * (lr1 / lr0) ** p


def set_lr(optimizer: Optimizer, lr: float) -> None:
    for group in optimizer.param_groups:
        group["lr"] = lr


@dataclass
class ParamGroup:
    """Trained tensors beside the Gaussians' rows that share one learning-rate schedule (a
    deformation field's planes, its decoder)."""

    name: str
    params: list[nn.Parameter]
    lr_at: Callable[[int], float]
    """The group's learning rate at a step (scene extent and batch factor included)."""


class OptimizerSet:
    """Every optimizer of a run, stepped together.

    ``gaussians``: one Adam per Gaussian parameter name (so the strategies' ops resize one tensor
    and its moments at a time); the means follow ``means_lr_at``, the others keep their rate.
    The model's other parameter groups share one Adam, each group at its own ``lr_at``; a model
    without such groups has none."""

    def __init__(self, gaussians: dict[str, Optimizer], means_lr_at: Callable[[int], float],
                 groups: list[ParamGroup], betas: tuple[float, float] = ADAM_BETAS) -> None:
        self.gaussians = gaussians
        self.means_lr_at = means_lr_at
        self.groups = {group.name: group for group in groups}
        self.shared: Optimizer | None = None
        if groups:
            self.shared = adam([{"params": g.params, "lr": g.lr_at(0), "name": g.name} for g in groups], betas)

    def step(self, step: int) -> float:
        """Set this step's learning rates, step every Adam and zero its gradients; returns the
        means' learning rate."""
        means_lr = self.means_lr_at(step)
        set_lr(self.gaussians["means"], means_lr)
        # torch's fused CPU Adam on two threads changed the last bits with the thread count (a
        # 30-step Seed+Split run at one and two threads, once another computation had started the
        # thread pool: 11.0310396 against 11.0310407 dB); on one thread it is the same bits at any
        # count and still 3x faster than the for-loop Adam on two (2.3 against 7.7 ms at 30,000
        # Gaussians). On a GPU the block changes nothing.
        if self.shared is not None:
            for group in self.shared.param_groups:
                group["lr"] = self.groups[group["name"]].lr_at(step)
        everyone = [*self.gaussians.values(), *([self.shared] if self.shared is not None else [])]
        with single_threaded_ops():
            fused = [opt for opt in everyone if isinstance(opt, FusedAdam)]
            fused_adam_step(fused)  # every step counter in one call (issue 69: fewer operators per step)
            for optimizer in everyone:
                if not isinstance(optimizer, FusedAdam):
                    optimizer.step()
                optimizer.zero_grad(set_to_none=True)
        return means_lr

    def lrs(self) -> dict[str, float]:
        """Each group's current learning rate by name (the Gaussians' and the model's others)."""
        rates = {name: float(opt.param_groups[0]["lr"]) for name, opt in self.gaussians.items()}
        if self.shared is not None:
            rates.update({group["name"]: float(group["lr"]) for group in self.shared.param_groups})
        return rates

    def state_dict(self) -> dict[str, Any]:
        """``optimizers``: the Gaussians' Adams by name; ``field_optimizer``: the shared Adam of the
        model's other groups, when there are any (the key checkpoints have always used)."""
        state: dict[str, Any] = {"optimizers": {k: opt.state_dict() for k, opt in self.gaussians.items()}}
        if self.shared is not None:
            state["field_optimizer"] = self.shared.state_dict()
        return state

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict` (Adam's moments follow their parameter's device)."""
        for name, opt in self.gaussians.items():
            opt.load_state_dict(state["optimizers"][name])
        if self.shared is not None:
            self.shared.load_state_dict(state["field_optimizer"])
