"""Dynamic scenes: canonical Gaussians deformed over time by a HexPlane field (4DGS).

The canonical Gaussians are the ordinary parameter dict, so every strategy and op works on
them unchanged; the deformation field is the model's one part (:class:`DeformationPart`), whose
planes and decoder are parameter groups of the run's optimizer set, out of the strategies' reach. A frame at
time t renders ``params_at(t)``: the canonical parameters plus the field's offsets there. The
projected 2D means are those of the deformed Gaussians, so the densification statistic is the
screen-space gradient of the deformed means, as in 4DGS.

Schedule (4DGS): a static warm-up (its "coarse" stage) trains the canonical Gaussians alone;
from ``start_frac`` of the run the deformation is on, its learning rates decaying
exponentially to the end, and the planes are regularised (total variation of the space planes,
smoothness in time and an L1 pull towards no motion of the space-time planes).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Mapping

import torch
from torch import Tensor, nn

from exploregs_plugin.model.deformation import (SPACE_PLANES, TIME_PLANES, DeformationField, plane_tv,
                                                robust_box, static_l1, time_smoothness)
from exploregs_plugin.model.gaussians import GaussianModel, GaussianModelConfig, ModelPart
from exploregs_plugin.model.optim import ParamGroup, exponential_lr

def deform_params(params: Mapping[str, Tensor], field: DeformationField, time: float) -> dict[str, Tensor]:
    """The raw parameters at ``time`` in [0, 1]: canonical means, quaternions and log-scales plus
    the field's offsets; opacity and colour stay canonical (4DGS)."""
    dx, dq, ds = field(params["means"], time)
    out = dict(params.items())
    out["means"] = params["means"] + dx
    out["quats"] = params["quats"] + dq
    out["scales"] = params["scales"] + ds
    return out


def params_at_time(params: Mapping[str, Tensor], field: DeformationField, time: float | None) -> Mapping[str, Tensor]:
    """What to render at ``time``: the canonical parameters during the static warm-up (the field
    not yet active), then :func:`deform_params` at ``time`` (None: 0, the first frame)."""
    if not bool(field.active):
        return params
    return deform_params(params, field, 0.0 if time is None else time)


@dataclass
class DeformationConfig:
    """The deformation field and its schedule (4DGS's settings, sized for CPU training)."""

    resolution: tuple[int, int, int, int] = (32, 32, 32, 16)
    """Plane cells along x, y, z (at the first level) and t. 4DGS: 64^3 x half the frame count."""
    multires: tuple[int, ...] = (1, 2)
    """Space-resolution factor of each level (the time resolution is the same at every level)."""
    features: int = 16
    """Features per plane and level (4DGS: 16 to 32)."""
    width: int = 32
    """Units of the decoder's layers (4DGS: 64 to 128; 32 keeps the field's cost below the
    rasterizer's on a CPU)."""
    depth: int = 1
    """Layers of the decoder's shared trunk (4DGS: 0 to 1 hidden layers)."""
    start_frac: float = 0.1
    """The deformation is switched on after this fraction of the run; before, the canonical
    Gaussians train alone (4DGS's coarse stage: 3k of 17k iterations). Shorter than 4DGS's: a
    long static warm-up fades the moving things away (their Gaussians see them in one frame
    only), and the deformation then has nothing to move (docs/dynamic.md)."""
    grid_lr: float = 1.6e-2
    """Initial learning rate of the planes (x scene extent): ten times 4DGS's 1.6e-3, as a CPU run
    makes about a tenth of its updates (docs/dynamic.md measures 1x, 3x and 10x)."""
    grid_lr_final: float = 1.6e-3
    """The planes' learning rate at the end of the run (x scene extent), reached by exponential
    decay from ``grid_lr`` after the deformation is switched on: a tenth of it, as in 4DGS."""
    mlp_lr: float = 1.6e-3
    """Initial learning rate of the decoder (x scene extent): ten times 4DGS's 1.6e-4."""
    mlp_lr_final: float = 1.6e-4
    """The decoder's learning rate at the end of the run (x scene extent), reached by exponential
    decay from ``mlp_lr`` after the deformation is switched on: a tenth of it, as in 4DGS."""
    plane_tv_weight: float = 2e-4
    """Total variation of the space planes (4DGS on DyNeRF: 2e-4)."""
    time_smoothness_weight: float = 1e-3
    """Second difference in time of the space-time planes (4DGS on DyNeRF: 1e-3)."""
    time_l1_weight: float = 1e-4
    """L1 of the space-time planes' distance from 1, i.e. from no motion (4DGS on DyNeRF: 1e-4)."""
    box_trim_percent: float = 1.0
    """The field's box spans these percentiles of the initial points (1 to 99 by default)."""
    box_margin: float = 0.1
    """... enlarged by this fraction of its size on each side."""

    def check(self) -> None:
        if not 0.0 <= self.start_frac <= 1.0:
            raise ValueError(f"deformation start_frac must be in [0, 1], got {self.start_frac}")
        if not 0.0 <= self.box_trim_percent < 50.0:
            raise ValueError(f"box_trim_percent must be in [0, 50), got {self.box_trim_percent}")
        for name in ("plane_tv_weight", "time_smoothness_weight", "time_l1_weight", "box_margin"):
            if getattr(self, name) < 0.0:
                raise ValueError(f"deformation {name} must be >= 0, got {getattr(self, name)}")


@dataclass
class DynamicGaussianModelConfig(GaussianModelConfig):
    """A Gaussian model whose frames are deformed over time (4DGS)."""

    deformation: DeformationConfig = field(default_factory=DeformationConfig)
    """The deformation field (--model.deformation.*)."""

    def setup(self, points: Tensor | None, points_rgb: Tensor | None, seed: int = 0) -> "DynamicGaussianModel":
        """``seed``: the run's seed, which draws the field's initial values."""
        self.deformation.check()
        static = super().setup(points, points_rgb)
        d = self.deformation
        box_min, box_max = robust_box(static.params["means"].detach(), d.box_trim_percent, d.box_margin)
        generator = torch.Generator().manual_seed(seed)
        deformation = DeformationPart(d, box_min.cpu(), box_max.cpu(), generator).to(static.params["means"].device)
        return DynamicGaussianModel(self, static.params, deformation)


class DeformationPart(DeformationField, ModelPart):
    """The deformation field as a model part: off during the static warm-up, then on (``active``,
    saved with its state); its planes ("grid") and decoder ("mlp") each a parameter group whose
    rate decays exponentially from the end of the warm-up to the last step; 4DGS's plane
    regularisers once it is on."""

    def __init__(self, config: DeformationConfig, box_min: Tensor, box_max: Tensor,
                 generator: torch.Generator | None = None) -> None:
        super().__init__(box_min, box_max, config.resolution, config.multires, config.features, config.width,
                         config.depth, generator)
        self.config = config

    def start_step(self, max_steps: int) -> int:
        """The step at which the deformation is switched on."""
        return int(round(self.config.start_frac * max_steps))

    def param_groups(self, scene_extent: float, max_steps: int, lr_scale: float = 1.0) -> list[ParamGroup]:
        """The planes ("grid") and decoder ("mlp"), each decaying exponentially from the end of the
        warm-up to the last step, x scene extent."""
        d = self.config
        start = self.start_step(max_steps)
        scale = scene_extent * lr_scale

        def decay(lr0: float, lr1: float):
            return lambda step: exponential_lr(lr0 * scale, lr1 * scale, (step - start) / max(max_steps - start, 1))

        return [ParamGroup("grid", self.grid_parameters(), decay(d.grid_lr, d.grid_lr_final)),
                ParamGroup("mlp", self.mlp_parameters(), decay(d.mlp_lr, d.mlp_lr_final))]

    def begin_step(self, step: int, max_steps: int) -> None:
        if step >= self.start_step(max_steps) and not bool(self.active):
            self.active.fill_(True)

    def regularization_loss(self) -> Tensor | None:
        """4DGS's plane regularisers, once the deformation is on (None before)."""
        if not bool(self.active):
            return None
        d = self.config
        total = self.box_min.new_zeros(())
        for planes in self.grid.planes():
            for i in SPACE_PLANES:
                total = total + d.plane_tv_weight * plane_tv(planes[i])
            for i in TIME_PLANES:
                # the time axis is the plane's rows (see deformation.plane_shape)
                total = total + d.time_smoothness_weight * time_smoothness(planes[i])
                total = total + d.time_l1_weight * static_l1(planes[i])
        return total


class DynamicGaussianModel(GaussianModel):
    """Canonical Gaussians (``params``) and their deformation over time (the part ``deformation``)."""

    config: DynamicGaussianModelConfig

    def __init__(self, config: DynamicGaussianModelConfig, params: nn.ParameterDict,
                 deformation: DeformationPart) -> None:
        super().__init__(config, params, {"deformation": deformation})

    @property
    def deformation(self) -> DeformationPart:
        return self.parts["deformation"]

    def params_at(self, time: float | None) -> Mapping[str, Tensor]:
        """:func:`params_at_time` of this model's Gaussians and field."""
        return params_at_time(self.params, self.deformation, time)
