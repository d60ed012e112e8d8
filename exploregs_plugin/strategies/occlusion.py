"""Occlusion-aware splitting: split candidates chosen by what alpha blending attenuates.

Alpha blending scales every gradient reaching a Gaussian by the transmittance T in front of it,
so an occluded Gaussian's screen-space gradient, the densification statistic, stays small even
where its pixels are wrong. This operator keeps, per Gaussian, the sums over its pixels of its
compositing weight alpha T and of its alpha (from the rasterizer, ``visibility_stats``): their
ratio is the mean transmittance T-bar in front of it. Its error signal is the view's
screen-space gradient norm divided by that view's T-bar (the attenuation undone), kept as an
exponential moving average over the views that see it. Random Splitting's budget then goes to
Gaussians drawn in proportion to

    mean scale x (1 - T-bar) x compensated gradient,

large, occluded Gaussians whose pixels still carry error, instead of by scale alone.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import torch
from torch import Tensor

from .default import ndc_gradient_norms
from .errors import StrategyError
from .exploration import ExplorationStrategy
from .guided import GuidedSeeding
from .observation import ViewObservation
from .row_ops import Params, num_gaussians
from .requirements import VISIBILITY_STATS
from .splitting import RandomSplitting, split_weights

if TYPE_CHECKING:
    from .default import DefaultStrategy

VIS_WEIGHT, VIS_ALPHA, OCC_ERROR = "vis_weight", "vis_alpha", "occ_error"
"""Per-Gaussian statistics: summed weight alpha T, summed alpha, and the compensated-gradient average."""


def mean_transmittance(vis_weight: Tensor, vis_alpha: Tensor, unseen: float = 1.0) -> Tensor:
    """T-bar = sum(alpha T) / sum(alpha) per Gaussian [N], in [0, 1]; ``unseen`` where nothing was
    summed (1: unoccluded, what splitting assumes; NaN leaves it out of an analysis' statistics)."""
    seen = vis_alpha > 0
    return torch.where(seen, vis_weight / vis_alpha.clamp_min(1e-12), torch.full_like(vis_alpha, unseen)).clamp(0.0, 1.0)


def occlusion_weights(log_scales: Tensor, vis_weight: Tensor, vis_alpha: Tensor, occ_error: Tensor) -> Tensor:
    """mean scale x (1 - T-bar) x compensated gradient, per Gaussian [N] (0 for non-finite rows)."""
    w = split_weights(log_scales) * (1.0 - mean_transmittance(vis_weight, vis_alpha)) * occ_error
    return torch.where(torch.isfinite(w), w, torch.zeros_like(w))


@dataclass
class OcclusionSplitting(RandomSplitting):
    """Random Splitting with candidates drawn by occlusion and compensated error (it requires the
    renderer's visibility statistics, which the pipeline then asks for)."""

    requires = frozenset({VISIBILITY_STATS})

    occlusion_t_floor: float = 0.05
    """Smallest T-bar the gradient is divided by (a fully hidden Gaussian's gradient is noise)."""
    occlusion_decay: float = 0.9
    """Weight of the old value in the moving average of the compensated gradient, per view that sees it."""

    def __post_init__(self) -> None:
        super().__post_init__()
        if not 0.0 < self.occlusion_t_floor <= 1.0 or not 0.0 <= self.occlusion_decay < 1.0:
            raise StrategyError("occlusion_t_floor must be in (0, 1] and occlusion_decay in [0, 1)")

    def observe(self, owner: DefaultStrategy, params: Params, state: dict[str, Any],
                view: ViewObservation) -> dict[str, int]:
        counts = super().observe(owner, params, state, view)
        n = num_gaussians(params)
        if n == 0:
            return counts
        if view.visibility is None:
            raise StrategyError(f"{type(self).__name__} needs the view's visibility statistics: the pipeline "
                                f"gives them to strategies whose requirements() include VISIBILITY_STATS")
        stats = state["stats"]
        vis = view.visibility.detach().to(params["means"].dtype)  # [N, 2]
        for key in (VIS_WEIGHT, VIS_ALPHA, OCC_ERROR):
            stats.setdefault(key, torch.zeros(n, device=params["means"].device))
        stats[VIS_WEIGHT] += vis[:, 0]
        stats[VIS_ALPHA] += vis[:, 1]
        grad = view.screen_gradient()
        if grad is None:
            return counts
        norm = ndc_gradient_norms(grad, view.width, view.height, view.n_cameras, view.downscale)
        t_view = mean_transmittance(vis[:, 0], vis[:, 1]).clamp_min(self.occlusion_t_floor)
        seen = view.visible() & torch.isfinite(norm) & (vis[:, 1] > 0)
        error = stats[OCC_ERROR]
        # a where over every row, not a boolean index (its nonzero reads its size from the device)
        averaged = self.occlusion_decay * error + (1.0 - self.occlusion_decay) * (norm / t_view)
        error.copy_(torch.where(seen, averaged, error))
        return counts

    def candidate_weights(self, params: Params, state: dict[str, Any]) -> Tensor:
        stats = state["stats"]
        if OCC_ERROR not in stats:  # nothing observed yet: the paper's rule
            return super().candidate_weights(params, state)
        return occlusion_weights(params["scales"], stats[VIS_WEIGHT], stats[VIS_ALPHA], stats[OCC_ERROR])


@dataclass
class OcclusionSplittingStrategy(ExplorationStrategy):
    """Occlusion-aware splitting on top of 3DGS adaptive density control."""

    splitting: OcclusionSplitting = field(default_factory=OcclusionSplitting)
    """Random Splitting with candidates drawn by occlusion and compensated error (near side)."""


@dataclass
class GuidedOcclusionStrategy(ExplorationStrategy):
    """Guided seeding (far side) + occlusion-aware splitting (near side) on top of 3DGS ADC."""

    splitting: OcclusionSplitting = field(default_factory=OcclusionSplitting)
    """Occlusion-aware splitting (near side), run first."""
    seeding: GuidedSeeding = field(default_factory=GuidedSeeding)
    """Guided seeding (far side), run after the splits."""
