"""Error-mass densification: Default's growth budget, spent on the Gaussians that render the most
error in the view that sees them best.

Three things keep the screen-space statistic of a Gaussian behind an occluder small (measured on
``builtin:nearside`` with ``eg-analyze nearside``, docs/results.md):

- it is the mean over every view whose frustum holds the Gaussian, most of which see it through
  the occluder;
- each view's gradient carries the transmittance T in front of it;
- over fine texture the per-pixel parts of a large Gaussian's gradient cancel: |sum_p g_p| is a
  small fraction of sum_p |g_p|.

The error mass of Gaussian i in view v,

    M_iv = e_v(mu_iv) * sum_p alpha_ip T_ip,

(the view's mean absolute error at the Gaussian's 2D centre times the light it delivers, the
renderer's visibility sum) is unsigned, so nothing cancels, carries T once, and is kept as the
maximum over the views of a densification window, so views that cannot see the Gaussian do not
dilute it. At every densification the number of Gaussians grown is Default's (those whose
statistic passes ``grow_grad2d``, within ``cap_max``), so the count follows Default's; a share
``error_share`` of them are the largest M, the rest the largest statistic. Clone or split by
size, as Default.

A negative result: on ``builtin:nearside`` it kept Default's count but lost 0.45 dB in the occluded
region (docs/results.md, "The near-side trap on builtin:nearside"). It lives outside
``exploregs_plugin`` and is registered as ``error-mass`` only when this folder is pip-installed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from exploregs_plugin.strategies.base import StrategyError
from exploregs_plugin.strategies.requirements import VIEW_ERRORS, VISIBILITY_STATS
from exploregs_plugin.strategies.default import DefaultStrategy
from exploregs_plugin.strategies.geometry import max_world_scale
from exploregs_plugin.strategies.observation import ViewObservation
from exploregs_plugin.strategies.row_ops import Params, num_gaussians

ERROR_MASS = "error_mass"
"""Per-Gaussian statistic: the largest error mass over the views of the current window."""


def error_mass(error: Tensor, means2d: Tensor, weight: Tensor, visible: Tensor) -> Tensor:
    """M = e(mu) * sum(alpha T) per Gaussian [N] for one view (0 where not visible, outside the
    image or not finite). error: [H, W] mean |render - target|; means2d: [N, 2] pixels (x, y);
    weight: [N] the view's sum of alpha T; visible: [N] bool."""
    h, w = error.shape
    x, y = means2d[:, 0], means2d[:, 1]
    inside = (x >= 0) & (x < w) & (y >= 0) & (y < h)
    xi = torch.nan_to_num(x, nan=0.0).floor().clamp(0, w - 1).long()
    yi = torch.nan_to_num(y, nan=0.0).floor().clamp(0, h - 1).long()
    mass = error[yi, xi].to(weight.dtype) * weight
    keep = visible & inside & torch.isfinite(mass)
    return torch.where(keep, mass, torch.zeros_like(mass))


def choose_growth(statistic: Tensor, mass: Tensor, n_grow: int, error_share: float) -> Tensor:
    """[N] bool: ``n_grow`` rows, round(error_share * n_grow) of them the largest ``mass`` (> 0),
    the rest the largest ``statistic`` among the others. Ties keep index order (stable sorts)."""
    n = statistic.shape[0]
    chosen = torch.zeros(n, dtype=torch.bool, device=statistic.device)
    n_grow = max(0, min(int(n_grow), n))
    if n_grow == 0:
        return chosen
    k_mass = min(int(round(error_share * n_grow)), int((mass > 0).sum()))
    if k_mass > 0:
        chosen[torch.sort(mass, descending=True, stable=True).indices[:k_mass]] = True
    rest = n_grow - k_mass
    if rest > 0:
        score = torch.where(chosen, torch.full_like(statistic, -math.inf), statistic)
        chosen[torch.sort(score, descending=True, stable=True).indices[:rest]] = True
    return chosen


@dataclass
class ErrorMassStrategy(DefaultStrategy):
    """3DGS adaptive density control whose growth budget (Default's count) goes to the Gaussians
    with the largest error mass in their best view."""

    requires = frozenset({VIEW_ERRORS, VISIBILITY_STATS})

    error_share: float = 1.0
    """Share of each densification's growth chosen by error mass (the rest by Default's statistic)."""

    def __post_init__(self) -> None:
        super().__post_init__()
        if not 0.0 <= self.error_share <= 1.0:
            raise StrategyError(f"error_share must be in [0, 1], got {self.error_share}")

    def observe(self, params: Params, state: dict[str, Any], view: ViewObservation) -> dict[str, int]:
        counts = super().observe(params, state, view)
        n = num_gaussians(params)
        if n == 0:
            return counts
        if view.error is None or view.visibility is None:
            raise StrategyError(f"{type(self).__name__} needs the view's error map and visibility statistics: "
                                f"declare VIEW_ERRORS and VISIBILITY_STATS in its requires")
        if view.means2d is None:
            return counts  # a view rendered by another rank carries no 2D means: it adds no error mass
        mass = error_mass(view.error.error.detach(), view.means2d.detach().reshape(n, 2).to(torch.float32),
                          view.visibility.detach()[:, 0].to(torch.float32), view.visible())
        stats = state["stats"]
        if ERROR_MASS not in stats:
            stats[ERROR_MASS] = torch.zeros(n, device=mass.device)
        stats[ERROR_MASS] = torch.maximum(stats[ERROR_MASS], mass.to(stats[ERROR_MASS].dtype))
        return counts

    def growth(self, params: Params, state: dict[str, Any]) -> tuple[Tensor, Tensor]:
        stats = state["stats"]
        avg_grad = stats["grad2d"] / stats["count"].clamp_min(1.0)
        # the budget: as many as Default's threshold grows (and the cap allows)
        n_grow = min(int((avg_grad > self.grow_grad2d).sum()), self.room(num_gaussians(params)))
        mass = stats.get(ERROR_MASS, torch.zeros_like(avg_grad))
        chosen = choose_growth(avg_grad, mass, n_grow, self.error_share)
        if ERROR_MASS in stats:
            # a new window: the next decision sees only its own views (the clones and children
            # Default's growth makes from these rows then start at zero too)
            stats[ERROR_MASS].zero_()
        small = max_world_scale(params["scales"].detach()) <= self.grow_scale3d * state["scene_scale"]
        return chosen & small, chosen & ~small
