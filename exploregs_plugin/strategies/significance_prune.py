"""Prune by significance while the set grows: keep only the Gaussians that paint the training images.

The significance of Gaussian j over a stretch of training views is its total compositing weight,

    S_j = sum_views sum_pixels alpha_j(p) T_j(p)

(:mod:`exploregs_plugin.model.significance`), which the renderer sums in the same pass as the
training image when asked (``VISIBILITY_STATS``): no extra pass. At a refinement the rule sorts
the Gaussians that the window's views drew by S_j and removes the least significant ones whose
weights add up to at most a share ``q`` of the total:

    prune the smallest k with  sum_{i <= k} S_(i) <= q sum_i S_i .

The share is a fraction of what the images show, so it reads the same at every resolution, view
count and opacity level, and the count it leaves follows the scene: where a few Gaussians paint
most of the pixels, the tail it cuts is long. A Gaussian that no view of the window drew is not
judged (its weight says nothing), and neither is any Gaussian in a window that began at an
opacity reset, whose weights measure the climb back from the reset value rather than what each
Gaussian paints.
"""

from __future__ import annotations

import torch
from torch import Tensor

from ..rasterizer.settings import VISIBILITY_PEAK
from .row_ops import Stats

WEIGHT, WEIGHT_PEAK, WEIGHT_VIEWS = "weight", "weight_peak", "weight_views"
"""Per-Gaussian statistics of the window: summed compositing weight (pixels), the largest weight at
one pixel (the peak) and the number of views that drew the Gaussian. Cleared at every refinement,
with the gradient statistics."""
WEIGHT_STATS = (WEIGHT, WEIGHT_PEAK, WEIGHT_VIEWS)


def accumulate_weights(stats: Stats, visibility: Tensor, visible: Tensor) -> None:
    """Add one view's visibility statistics [N, 3] (per Gaussian, over the view's pixels: the sum of
    alpha T, the sum of alpha, the largest alpha T) and its drawn mask [N] to the window's
    statistics (created, zeros, on first use). A non-finite value adds nothing (the view still
    counts as having drawn the row: it is judged on the rest)."""
    n = visibility.shape[0]
    for key in WEIGHT_STATS:  # each on first use (a window resumed from before the peak lacks it)
        if key not in stats:
            stats[key] = torch.zeros(n, dtype=torch.float32, device=visibility.device)
    values = visibility.detach().to(torch.float32)
    values = torch.where(torch.isfinite(values), values, 0.0)
    stats[WEIGHT] += values[:, 0]
    torch.maximum(stats[WEIGHT_PEAK], values[:, VISIBILITY_PEAK], out=stats[WEIGHT_PEAK])
    stats[WEIGHT_VIEWS] += visible


def least_significant(weights: Tensor, views: Tensor, share: float, score: Tensor | None = None) -> Tensor:
    """[N] bool: of the rows drawn at least once (``views`` > 0), the ones of least ``score``
    (default: ``weights``; the cuts pass :func:`~exploregs_plugin.model.significance.cut_order`'s
    weight x peak) whose ``weights`` add up to at most ``share`` of theirs all (float64 sums; ties
    in index order, a stable sort, so the same sums give the same rows on any thread count).
    Nothing when the drawn rows paint nothing at all, or ``share`` <= 0."""
    n = weights.shape[0]
    prune = torch.zeros(n, dtype=torch.bool, device=weights.device)
    judged = views > 0
    if share <= 0.0 or n == 0:
        return prune
    w = torch.where(judged, weights.to(torch.float64).clamp_min(0.0), 0.0)
    total = w.sum()
    rank = w if score is None else torch.where(torch.isfinite(score), score.to(torch.float64), 0.0)
    # unjudged rows sort last (+inf) and can never fall under the share
    order = torch.sort(torch.where(judged, rank, torch.inf), stable=True).indices
    below = (torch.cumsum(w[order], 0) <= share * total) & judged[order] & (total > 0)
    prune[order] = below
    return prune


def window_follows_reset(step: int, window: int, reset_every: int) -> bool:
    """Whether the window of ``window`` steps that ends at refinement ``step`` began at or after an
    opacity reset (resets come at positive multiples of ``reset_every``, after that step's prune)."""
    last_reset = (step - 1) // reset_every * reset_every
    return last_reset > 0 and last_reset >= step - window
