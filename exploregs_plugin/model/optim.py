"""Adam optimizers with the 3DGS learning rates, one per parameter name."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

ADAM_EPS = 1e-15  # 3DGS uses a tiny epsilon: Adam steps stay near lr even for tiny gradients


@dataclass
class OptimizerConfig:
    """3DGS learning rates (Kerbl et al. 2023 reference values)."""

    means_lr: float = 1.6e-4
    """Initial position learning rate, multiplied by the scene extent."""
    means_lr_final: float = 1.6e-6
    """Final position learning rate (x scene extent), reached by exponential decay at the last step."""
    scales_lr: float = 5e-3
    quats_lr: float = 1e-3
    opacities_lr: float = 5e-2
    sh0_lr: float = 2.5e-3
    shN_lr: float = 2.5e-3 / 20.0
    """Higher-order SH learn 20x slower than the DC term, as in 3DGS."""

    def base_lrs(self, scene_extent: float) -> dict[str, float]:
        return {
            "means": self.means_lr * scene_extent,
            "scales": self.scales_lr,
            "quats": self.quats_lr,
            "opacities": self.opacities_lr,
            "sh0": self.sh0_lr,
            "shN": self.shN_lr,
        }

    def setup(self, params: nn.ParameterDict, scene_extent: float) -> dict[str, torch.optim.Adam]:
        """One Adam per parameter name (so ops can resize one tensor and its moments at a time)."""
        lrs = self.base_lrs(scene_extent)
        return {
            name: torch.optim.Adam([{"params": [params[name]], "lr": lrs[name], "name": name}], eps=ADAM_EPS)
            for name in params.keys()
        }

    def means_lr_at(self, step: int, max_steps: int, scene_extent: float) -> float:
        """Exponential decay lr(t) = lr0 (lr1 / lr0)^(t / max_steps), both scaled by the extent."""
        t = min(max(step, 0), max_steps) / max(max_steps, 1)
        lr0, lr1 = self.means_lr * scene_extent, self.means_lr_final * scene_extent
        return lr0 * (lr1 / lr0) ** t


def set_lr(optimizer: torch.optim.Optimizer, lr: float) -> None:
    for group in optimizer.param_groups:
        group["lr"] = lr
