"""The count a scene needs, decided on views the optimiser does not fit (``cap_max 'validated'``).

While the rule decides, a few training views are held out: never trained on, rendered only to
score the model. The set grows to a ceiling, trains, and at the end of growth the trainer tries
it cut to a few smaller counts (the most significant Gaussians of each, :mod:`exploregs_plugin.engine.count_trial`),
each candidate fine-tuned alike from the same snapshot on the same views: a paired comparison, in
which what differs between two candidates is the count alone. The rule picks the smallest
candidate whose held-out PSNR is not worse than the best candidate's by more than a tolerance,
read per held-out view: with d_v = p_best(v) - p_c(v) on view v of k,

    mean(d) + sd(d) / sqrt(k) <= tolerance,

the paired deficit plus its standard error. The standard error makes a handful of views
conservative: a smaller count is taken only where the views agree that it costs little, not
where a mean over them happens to be small. The views then return to training, and the set is
cut to the pick. Nothing here is random, so the decision is the same on any thread count.
"""

from __future__ import annotations

import math
from typing import Sequence

VALIDATED = "validated"
"""``cap_max = 'validated'``: the count is decided on held-out views by the paired cut."""
COUNT_START, COUNT_CAP, COUNT_TRIAL, COUNT_NOTE = ("count_start", "count_cap", "count_trial", "count_note")
"""State of the validated count: the count at the first refinement (MCMC's ceiling's base; None
before it), the count kept (None while it is undecided), each candidate's (count, mean held-out
PSNR, PSNR of each held-out view) from the trial, and the one line that says what was kept and why ('' before)."""
TRIAL_SHARE = 0.01
"""A candidate's fine-tuning steps as a share of the run's steps (300 of 30k)."""


def validated_state() -> dict:
    """The validated count's state at the start of a run (kept in the strategy state: checkpointed)."""
    return {COUNT_START: None, COUNT_CAP: None, COUNT_TRIAL: [], COUNT_NOTE: ""}


MIN_VIEWS = 8
"""Training views a run needs before the rule holds some out (it keeps at least 6 to train on)."""


def held_out_count(n_train: int) -> int:
    """Views to hold out of ``n_train``: one in twelve, at least 2 and at most 8 (0 below MIN_VIEWS)."""
    if n_train < MIN_VIEWS:
        return 0
    return min(8, max(2, n_train // 12))


def held_out_indices(n_train: int) -> list[int]:
    """The held-out training indices: :func:`evenly_spread` over the capture order."""
    return evenly_spread(n_train, held_out_count(n_train))


def evenly_spread(n: int, k: int) -> list[int]:
    """``k`` of the indices 0..n-1 (all of them when ``k`` >= ``n``), evenly spread over the capture
    order, ``floor((i + 1/2) n / k)``: no stretch of the path is scored twice and none left out;
    deterministic."""
    k = min(k, n)
    return [int((i + 0.5) * n / k) for i in range(k)]


CHECK_VIEWS = 24
"""Training views the end-of-run cut's check renders (:func:`evenly_spread`; all of a smaller
capture), so that a capture of hundreds of photos pays 24 renders a candidate, not one per photo.
Over all 58 of fox's views the paired deficit's standard error was 0.003-0.011 dB at the shares the
check keeps (docs/strategies.md); 24 views make it about 1.6 times that, still small next to the
0.1 dB tolerance."""


def candidate_counts(n: int, cuts: Sequence[float]) -> list[int]:
    """The counts to try for a set of ``n``: ``floor(n c)`` for each cut c in (0, 1], at least 1,
    without repeats, largest first (the whole set, c = 1, is always one of them)."""
    counts = {n} | {max(1, int(math.floor(n * c))) for c in cuts}
    return sorted(counts, reverse=True)


def paired_deficit(best: Sequence[float], other: Sequence[float]) -> float:
    """mean(d) + sd(d) / sqrt(k) of the per-view deficits d_v = best_v - other_v (dB) over k views:
    the deficit of ``other`` with its standard error (sd with k - 1; 0 for one view). Not finite
    when a PSNR is not."""
    k = len(best)
    if k == 0 or len(other) != k:
        raise ValueError(f"a paired deficit needs the same views on both sides, got {k} and {len(other)}")
    d = [b - o for b, o in zip(best, other)]
    mean = sum(d) / k
    if k == 1:
        return mean
    var = sum((x - mean) ** 2 for x in d) / (k - 1)
    return mean + math.sqrt(max(var, 0.0) / k)


def pick_count(counts: Sequence[int], per_view: Sequence[Sequence[float]], tolerance: float) -> int:
    """The index of the candidate to keep: of ``counts`` (any order) scored ``per_view[i]`` (the
    held-out views' PSNRs, the same views in the same order for every candidate), the fewest
    Gaussians whose :func:`paired_deficit` against the best candidate (highest mean PSNR) is at
    most ``tolerance`` dB. A candidate with a non-finite PSNR is never kept; if none is finite the
    largest set is."""
    if len(counts) != len(per_view) or not counts:
        raise ValueError(f"one score list per candidate, got {len(counts)} counts and {len(per_view)} lists")
    finite = scored_candidates(per_view)
    if not finite:
        return max(range(len(counts)), key=lambda i: counts[i])
    best = max(finite, key=lambda i: (mean_psnr(per_view[i]), counts[i]))
    kept = [i for i in finite if i == best or paired_deficit(per_view[best], per_view[i]) <= tolerance]
    return min(kept, key=lambda i: (counts[i], i))


def scored_candidates(per_view: Sequence[Sequence[float]]) -> list[int]:
    """The indices of the candidates with a finite PSNR on every held-out view (and at least one
    view): the only ones :func:`pick_count` may keep."""
    return [i for i, scores in enumerate(per_view) if scores and all(math.isfinite(p) for p in scores)]


def mean_psnr(scores: Sequence[float]) -> float:
    """The mean of per-view PSNRs (dB): the figure the decision line prints for each candidate."""
    return sum(scores) / len(scores) if scores else float("nan")
