"""The cuts' weights, summed from the training renders of the epoch before each.

The cut after the last step (:meth:`Strategy.final_cut`) ranks each Gaussian by its visibility
statistics over every training view: its compositing weight S_j = sum_v sum_p alpha_j T_j, its
summed alpha (> 0 where some view drew it), its peak weight and its weight in the view that needs it
most (:func:`exploregs_plugin.model.significance.visibility_totals`). Rendering every view once more for
them costs one render per view after the last step: on the 252-photo capture at 800 x 533 (220
training views), 98 s of the cut's 143 s (docs/strategies.md).

The run renders every view once per epoch anyway. In its last complete epoch (the last permutation
of the training views that the run's remaining draws finish) the renderer sums the same statistics
in the pass that draws each training image, and the cut reads those sums: no pass of its own
(which draws are that epoch's: :meth:`~exploregs_plugin.data.datamanager.DataManager.last_epoch_draws`).
The settled cut (``DefaultStrategy.settled_cut_iter``, 0.8 of the run) reads the same sums
of the whole epoch that ends before it, and drops them; the end-of-run cut then sums its own.
The price is weights from parameters up to one epoch old, which after the set stops growing only the
optimiser moves; so the window counts only once the strategy no longer grows (a draw at or after
``refine_stop_iter``) and only renders at full size (a coarse-to-fine level's pixels weigh less).
Where the window opened inside its epoch (growth ended, or the settled cut came, after the epoch
began: on the 252-photo capture, 220 training views and 300 steps after the settled cut, the end-of-run
cut's epoch began 100 draws before it), the sums hold part of the epoch, each view at most once, and
name the views they hold: the cut renders only the views they lack and adds them (on that capture 100
renders instead of 220). Sums that cannot be completed so (views held out, a checkpoint whose sums do
not name their views or hold three columns) are not used: the cut renders every view itself.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from exploregs_plugin.model.significance import CUT_COLUMNS, add_totals_, add_view_

FINAL_WEIGHTS = "final_weights"
"""Key in the strategy's row statistics (``state["stats"]``, so every row operation keeps them in
step with the rows): [N, 4] float64, the next cut's statistics over its window's views (``CUT_COLUMNS``)."""
FINAL_VIEWS = "final_weight_views"
"""Key in the strategy's state: how many views the sums hold (whole when it equals the training views)."""
FINAL_SEEN = "final_weight_seen"
"""Key in the strategy's state: the training views (indices) whose renders the sums hold, in the order
summed (what a window that opened inside its epoch lacks: :func:`missing_views`)."""


def add_window_view(state: dict[str, Any], visibility: Tensor, view: int | None = None) -> None:
    """Add one of a cut's window's training renders (its visibility statistics [N, 3], the rows of
    the set it was drawn from; ``view``: its training index) to the window's statistics
    (``add_view_``), created on first use. A non-finite entry adds nothing (as
    :func:`exploregs_plugin.strategies.significance_prune.accumulate_weights`). Sums of another width
    (a checkpoint of a version whose window held [N, 3]) take no more views and are never whole: the
    cut renders the views itself."""
    stats = state["stats"]
    more = visibility.detach().to(torch.float64)
    if FINAL_WEIGHTS not in stats:
        stats[FINAL_WEIGHTS] = more.new_zeros(more.shape[0], len(CUT_COLUMNS))
    if stats[FINAL_WEIGHTS].shape[1] == len(CUT_COLUMNS):
        add_view_(stats[FINAL_WEIGHTS], torch.where(torch.isfinite(more), more, 0.0))
    if view is not None:
        state[FINAL_SEEN] = [*state.get(FINAL_SEEN, []), int(view)]
    state[FINAL_VIEWS] = window_views(state) + 1


def missing_views(state: dict[str, Any], views: int) -> list[int] | None:
    """The training views (indices below ``views``) whose renders the window's sums lack, where the
    sums can be completed: of ``CUT_COLUMNS``, each view at most once and every one named. None
    where they cannot (no sums, another width, views not named: a checkpoint of a version that did
    not name them); [] where they are whole."""
    sums = state.get("stats", {}).get(FINAL_WEIGHTS)
    seen = state.get(FINAL_SEEN, [])
    if (sums is None or sums.shape[1] != len(CUT_COLUMNS) or len(seen) != window_views(state)
            or len(set(seen)) != len(seen) or not all(0 <= v < views for v in seen)):
        return None
    held = set(seen)
    return [v for v in range(views) if v not in held]


def complete_window(state: dict[str, Any], rendered: Tensor, views: list[int]) -> None:
    """Take the statistics ``rendered`` [N, 4] (``CUT_COLUMNS``, one render of each of ``views``:
    those :func:`missing_views` named) into the window's sums: the sums added, the peak and the view
    weight the larger (each a maximum over views)."""
    sums = state["stats"][FINAL_WEIGHTS]
    add_totals_(sums, rendered.to(sums.dtype))
    state[FINAL_SEEN] = [*state.get(FINAL_SEEN, []), *views]
    state[FINAL_VIEWS] = window_views(state) + len(views)


def window_views(state: dict[str, Any]) -> int:
    """How many views the window's sums hold so far."""
    return int(state.get(FINAL_VIEWS, 0))


def window_totals(state: dict[str, Any], views: int) -> Tensor | None:
    """The window's statistics [N, 4] where they hold exactly one whole epoch of ``views`` training
    views, else None (the cut then renders them)."""
    sums = state.get("stats", {}).get(FINAL_WEIGHTS)
    whole = sums is not None and sums.shape[1] == len(CUT_COLUMNS) and window_views(state) == views
    return sums if whole else None


def clear_window(state: dict[str, Any]) -> None:
    """Drop the window's sums (after the cut has read them: the last checkpoint does not carry them)."""
    state.get("stats", {}).pop(FINAL_WEIGHTS, None)
    state.pop(FINAL_VIEWS, None)
    state.pop(FINAL_SEEN, None)
