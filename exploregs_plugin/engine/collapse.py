"""A training run that collapses stops, instead of training on to a useless result with exit 0.

Why a watch on the training PSNR: a learning rate set far too high makes the renders' colours and
sizes run away, and the PSNR falls step after step long before a NaN appears (x1000 on
``builtin:tiny``: 9 dB at the start, -8 dB seven steps later, then NaN). A step's PSNR depends on
its view far more than on the step: on ``beer`` the training views alternate between about 18 and
28 dB at step 300 of a healthy run. So when a step renders one view, the watch compares it with
the same view's own best since the last restart (a healthy run only climbs, view by view), and
follows a running mean of those differences; with no view named (a batch of views, whose mean
PSNR varies less) it follows the running mean of the PSNR itself. An opacity reset (which makes
every Gaussian nearly transparent on purpose, and the PSNR drop for a while) starts it afresh, and
so does a refinement that removes a large share of the set: on ``beer`` at the full schedule the
first refinement after the first opacity reset (step 3100, where the world-size prune starts) made
the training PSNR fall 11 dB below the views' records in a healthy run. A world-size prune starts
it afresh whatever its share: on ``beer`` at ``--data-factor 4`` (Default, seed 2, 1500 steps) the
refinement at step 300 removed 261 rows over the size limit of 5542 (and 66 faint ones, 5.9% in
all), the training PSNR fell from about 23 to 7-10 dB for twenty steps and the watch stopped a run
that, without it, ends at 27.25 dB with the other seeds (a row larger than a tenth of the scene
paints much of every view that sees it).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Hashable

LIKELY_CAUSE = "a learning rate too high? (--optim.*-lr)"
RESTART_PRUNED_SHARE = 0.1
"""A step that pruned at least this share of its Gaussians starts the watch afresh."""


def deliberate_setback(counts: dict[str, int], num_gaussians: int) -> bool:
    """Whether a step's strategy events set the renders back on purpose: an opacity reset, a prune
    of rows over the world-size limit (``pruned_too_big``, any number), or a prune of at least
    RESTART_PRUNED_SHARE of the set (``num_gaussians``: the count after it)."""
    pruned = int(counts.get("pruned", 0))
    return (bool(counts.get("opacity_reset", 0)) or int(counts.get("pruned_too_big", 0)) > 0
            or pruned >= RESTART_PRUNED_SHARE * max(num_gaussians + pruned, 1))


class CollapseError(RuntimeError):
    """The run's training PSNR or loss collapsed; the message names the likely cause."""


@dataclass
class CollapseWatch:
    """Follows the training PSNR and loss of every step; :meth:`update` says when the run collapsed."""

    drop_db: float = 10.0
    """Collapse: the running-mean PSNR this many dB below its best."""
    loss_growth: float = 10.0
    """Collapse: the running-mean loss this many times its lowest (the loss grows without bound)."""
    weight: float = 0.5
    """Weight of the newest step in the running means of the raw PSNR and loss (about two steps
    of memory: a batch's mean PSNR varies little from step to step)."""
    view_weight: float = 0.125
    """Weight of the newest step in the running means of the per-view differences (about eight
    views of memory). A healthy run dips after each refinement: on beer at 120 pixels high,
    steps 3000-5000 (after the first opacity reset), this mean reached 6.6 dB below the views'
    records at 0.125 and 11.6 dB at 0.5, which stopped that run."""
    _psnr: float = field(default=0.0, repr=False)
    _loss: float = field(default=0.0, repr=False)
    _best: tuple[float, int] = field(default=(-math.inf, -1), repr=False)
    _lowest: float = field(default=math.inf, repr=False)
    _restart: bool = field(default=True, repr=False)
    _views: dict[Hashable, tuple[float, float, int]] = field(default_factory=dict, repr=False)
    _drop: float | None = field(default=None, repr=False)
    _growth: float | None = field(default=None, repr=False)

    def update(self, step: int, psnr: float, loss: float, restart: bool = False,
               view: Hashable | None = None) -> str | None:
        """Take step ``step``'s PSNR and loss; return why the run collapsed, or None. ``restart``:
        the step reset the opacities after its render, so the means and records start again from
        the next step (the first one rendered with the reset opacities). ``view``: the one view
        the step rendered (its index), so the step is judged against that view's own record."""
        if view is not None:
            return self._update_view(step, psnr, loss, restart, view)
        if self._restart:
            self._psnr, self._loss = psnr, loss
            self._best, self._lowest = (-math.inf, -1), math.inf
        else:
            self._psnr += self.weight * (psnr - self._psnr)
            self._loss += self.weight * (loss - self._loss)
        self._restart = restart
        if not (math.isfinite(self._psnr) and math.isfinite(self._loss)):
            return None  # the pipeline's own check names the non-finite value
        if self._psnr > self._best[0]:
            self._best = (self._psnr, step)
        self._lowest = min(self._lowest, self._loss)
        best, best_step = self._best
        if best - self._psnr > self.drop_db:
            return (f"the training PSNR fell to {self._psnr:.1f} dB, {best - self._psnr:.1f} dB below its best "
                    f"({best:.1f} dB at step {best_step}): the run diverged, {LIKELY_CAUSE}")
        if self._lowest > 0 and self._loss > self.loss_growth * self._lowest:
            return (f"the training loss grew to {self._loss:.3g}, {self._loss / self._lowest:.0f}x its lowest: "
                    f"the run diverged, {LIKELY_CAUSE}")
        return None

    def _update_view(self, step: int, psnr: float, loss: float, restart: bool, view: Hashable) -> str | None:
        """The per-view rule: running means of (PSNR - the view's best PSNR) and of (loss / the
        view's lowest loss), over the steps whose view was seen before since the last restart."""
        if self._restart:
            self._views, self._drop, self._growth = {}, None, None
        self._restart = restart
        if not (math.isfinite(psnr) and math.isfinite(loss)):
            return None  # the pipeline's own check names the non-finite value
        record = self._views.get(view)
        self._views[view] = (max(psnr, record[0]), min(loss, record[1]), record[2] if psnr <= record[0] else step) \
            if record is not None else (psnr, loss, step)
        if record is None:
            return None
        best, lowest, best_step = record
        drop, growth = best - psnr, loss / lowest if lowest > 0 else 1.0
        self._drop = drop if self._drop is None else self._drop + self.view_weight * (drop - self._drop)
        self._growth = growth if self._growth is None else self._growth + self.view_weight * (growth - self._growth)
        if self._drop > self.drop_db:
            return (f"the training PSNR fell to {psnr:.1f} dB on view {view}, {self._drop:.1f} dB below the "
                    f"views' own best (recent steps; this one's {best:.1f} dB at step {best_step}): the run "
                    f"diverged, {LIKELY_CAUSE}")
        if self._growth > self.loss_growth:
            return (f"the training loss grew to {self._growth:.0f}x the views' own lowest (recent steps; "
                    f"{loss:.3g} on view {view}): the run diverged, {LIKELY_CAUSE}")
        return None
