"""A training run that collapses stops, instead of training on to a useless result with exit 0.

Why a watch on the training PSNR: a learning rate set far too high makes the renders' colours and
sizes run away, and the PSNR falls step after step long before a NaN appears (x1000 on
``builtin:tiny``: 9 dB at the start, -8 dB seven steps later, then NaN). A step's PSNR depends on
its view, so the watch follows a running mean, and an opacity reset (which makes every Gaussian
nearly transparent on purpose, and the PSNR drop for a while) starts it afresh.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

LIKELY_CAUSE = "a learning rate too high? (--optim.*-lr)"


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
    """Weight of the newest step in the running means (about two steps of memory)."""
    _psnr: float = field(default=0.0, repr=False)
    _loss: float = field(default=0.0, repr=False)
    _best: tuple[float, int] = field(default=(-math.inf, -1), repr=False)
    _lowest: float = field(default=math.inf, repr=False)
    _restart: bool = field(default=True, repr=False)

    def update(self, step: int, psnr: float, loss: float, restart: bool = False) -> str | None:
        """Take step ``step``'s PSNR and loss; return why the run collapsed, or None. ``restart``:
        the step reset the opacities after its render, so the means and records start again from
        the next step (the first one rendered with the reset opacities)."""
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
