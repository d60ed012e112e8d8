"""The count a scene needs, decided on views the optimiser does not fit (``cap_max 'validated'``).

While the rule decides, a few training views are held out: never trained on, rendered only to
score the model. Growth runs in windows of ``window`` refinements that alternate, hold first:
hold (no growth), grow, hold, grow, ... The held-out PSNR p_i is read at the start of window i,
so window i gains g_i = p_(i+1) - p_i. A hold window's gain is what training alone adds at that
time; a grow window's is training plus the new Gaussians. The contrast of grow window i is

    c_i = g_i - (g_(i-1) + g_(i+1)) / 2,

its gain beyond the mean of the hold windows on either side (training's own gain falls slowly
over the run, so the mean of the windows before and after is the estimate at the grow window's
time). Growth goes on while c_i >= min_gain dB and stops for good at the first window that did
not pay (or whose readings are not finite): the count then is the scene's. The rule reads the
held-out views once per window, at most a few renders every few hundred steps, and nothing
random: the same decision on any thread count.
"""

from __future__ import annotations

import math

MIN_VIEWS = 8
"""Training views a run needs before the rule holds some out (it keeps at least 6 to train on)."""


def held_out_count(n_train: int) -> int:
    """Views to hold out of ``n_train``: one in twelve, at least 2 and at most 8 (0 below MIN_VIEWS)."""
    if n_train < MIN_VIEWS:
        return 0
    return min(8, max(2, n_train // 12))


def held_out_indices(n_train: int) -> list[int]:
    """The held-out training indices: evenly spread over the capture order (``floor((i + 1/2) n / k)``),
    so that no stretch of the path is scored twice and none left out; deterministic."""
    k = held_out_count(n_train)
    return [int((i + 0.5) * n_train / k) for i in range(k)]


def window_grows(refinement: int, window: int) -> bool:
    """Whether refinement ``refinement`` (0 = the first of the run) lies in a grow window."""
    return (refinement // window) % 2 == 1


def reading_due(refinement: int, window: int) -> bool:
    """Whether the held-out PSNR is read at this refinement: the start of every window."""
    return refinement % window == 0


def growth_contrast(readings: list[float]) -> float | None:
    """The contrast c of the grow window that the newest reading closes the hold window after,
    or None when the newest reading closes no such window. ``readings`` are p_0 .. p_m, one per
    window start; grow windows are the odd ones, so c is due at every odd m >= 3 (window m - 2).
    Not finite when a reading is not."""
    m = len(readings) - 1
    if m < 3 or m % 2 == 0:
        return None
    before, grown, after = (readings[j + 1] - readings[j] for j in (m - 3, m - 2, m - 1))
    return grown - 0.5 * (before + after)


def growth_paid(contrast: float, min_gain: float) -> bool:
    """Whether a grow window paid back: its contrast is finite and at least ``min_gain`` dB."""
    return math.isfinite(contrast) and contrast >= min_gain
