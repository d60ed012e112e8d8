"""Default: 3DGS adaptive density control (Kerbl et al. 2023).

Per step (inside the refinement window) the screen-space gradient statistic of every visible
Gaussian is accumulated: ||dL/d(mean2d)|| in NDC units (pixel gradient x W/2, H/2), summed and
divided by the number of views in which the Gaussian was visible. Every ``refine_every`` steps:
clone Gaussians whose statistic exceeds ``grow_grad2d`` and whose largest scale is at most
``grow_scale3d`` x extent, split the larger ones, prune opacity < ``prune_opa`` (and, after the
first opacity reset, world size > ``prune_scale3d`` x extent), then clear the statistics. Every
``reset_every`` steps the opacities are clamped to ``reset_opacity``. With ``split_absgrad2d``
(AbsGS's rule, an option) the larger ones are split also when the absolute sums of their pixels'
gradients, a second statistic kept beside the first, exceed it.

Exploration enters through four hooks: :meth:`DefaultStrategy.observe` (each view, inside the
window), :meth:`DefaultStrategy.explore` (every step, after densification and before the opacity
reset), :meth:`DefaultStrategy.size_prune_factor` and :meth:`DefaultStrategy.extra_prune` (more
rows to remove at a refinement step). :class:`~exploregs_plugin.strategies.exploration.ExplorationStrategy`
implements them by running its operators in order; a subclass may also override them directly.
"""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass
from typing import Any, Callable, ClassVar, Sequence

import torch
from torch import Tensor

from . import row_ops
from .observation import ViewObservation
from .base import StepContext, Strategy, StrategyError, require_generator
from .count_rule import paired_deficit
from .geometry import max_world_scale
from .requirements import ABSOLUTE_GRADIENT, VISIBILITY_STATS
from .row_ops import Optimizers, Params, Stats, num_gaussians
from ..model.significance import cut_order, visibility_cut_order
from ..schedule import Schedule
from .significance_prune import (WEIGHT, WEIGHT_PEAK, WEIGHT_STATS, WEIGHT_VIEWS, accumulate_weights,
                                 least_significant, window_follows_reset)


GRAD_STATS = ("grad2d", "count")
"""Per-Gaussian statistics of the gradient criterion, cleared after every densification."""
ABS_GRAD_STATS = ("absgrad2d", "abscount")
"""The same for the absolute sums that ``split_absgrad2d`` reads, beside GRAD_STATS."""
REFERENCE_HEIGHT = 720
"""The image height (pixels) at which Default's threshold is 3DGS's 0.0002 (beer's capture; 3DGS's
own scenes are 545 to 1080 pixels high)."""
CHECKED_SHARES = (0.005, 0.01, 0.02, 0.03, 0.05, 0.1)
"""The shares the checked cuts try after ``final_weight_share``, in order, each kept only while
the training views say the cut costs at most its tolerance (``final_cut_tolerance`` after the last
step, ``settled_cut_tolerance`` for the settled cut; steps of about 1.5-2x)."""
SIGNIFICANCE_PRUNED, SIGNIFICANCE_NOTE = "significance_pruned", "significance_note"
"""State of the significance prune: the rows it has removed in all, and the line that says the
count it left at the end of growth, and why ('' before)."""
CUT_NOTES = "cut_notes"
"""The strategy state's list of the cuts' lines (:meth:`DefaultStrategy.cut_lines`); a checkpoint
made before it holds none."""


# ---------------------------------------------------------------------------- pure functions
def accumulate_grad_stats(
    stats: Stats,
    pixel_grads: Tensor,
    visible: Tensor,
    width: int,
    height: int,
    n_cameras: int = 1,
    downscale: int = 1,
    reference_height: int | None = None,
    names: tuple[str, str] = GRAD_STATS,
) -> Tensor:
    """Add this step's NDC gradient norms to ``stats["grad2d"]`` and views to ``stats["count"]``
    (to the two ``names`` given: another statistic kept beside it).

    pixel_grads: [C, N, 2] dL/d(mean2d) in pixels, or [N, 2] for one camera; visible: [C, N]
    (or [N]) bool. The stats are created (zeros [N]) on first use; ``reference_height``: see
    :func:`ndc_gradient_norms`. Rows with a non-finite gradient are skipped (neither summed nor
    counted); returns how many visible rows were skipped, a 0-dim long tensor on the gradients'
    device (read only where it is logged: nothing here waits for the device).
    """
    n = pixel_grads.shape[-2]
    total, count = names
    if total not in stats:
        stats[total] = torch.zeros(n, device=pixel_grads.device)
        stats[count] = torch.zeros(n, device=pixel_grads.device)
    if stats[total].shape[0] != n:
        raise StrategyError(
            f"strategy statistics have {stats[total].shape[0]} rows but the gradient has {n}: "
            f"the Gaussian set was changed without strategies.row_ops"
        )
    norms = ndc_gradient_norms(pixel_grads, width, height, n_cameras, downscale, reference_height)
    take = visible & torch.isfinite(norms)
    # Masked adds, camera by camera, instead of an index_add_ over torch.where(take): a nonzero
    # has to read its size from the device. The same sums in the same order (x + 0 = x for the
    # rows left out: the statistics are never -0). One camera's tensors are added as they are:
    # each select is one more operator a step (docs/training.md, "Operators per step").
    per_camera = [(norms, take)] if norms.dim() == 1 else zip(norms, take)
    for camera_norms, camera_take in per_camera:
        stats[total] += torch.where(camera_take, camera_norms, 0.0)
        stats[count] += camera_take
    return (visible ^ take).sum()  # visible and not finite


def ndc_gradient_norms(pixel_grads: Tensor, width: int, height: int, n_cameras: int = 1,
                       downscale: int = 1, reference_height: int | None = None) -> Tensor:
    """|dL/d(mean2d)| in NDC units, float32: [..., 2] pixel gradients -> [...].

    NDC spans [-1, 1] over W (H) pixels: d/d(ndc) = d/d(pixel) * W/2 (H/2). The n_cameras
    factor undoes the loss's mean over a batch of views, as gsplat does.

    ``downscale`` s > 1 (a coarse-to-fine level; W, H are the level's): the norm is divided by s,
    so that the threshold means at every level what it means at full size. Why, for the L1 loss
    L = (1/N) sum_p |r_p| over the level's N = W H pixels (the photometric loss is 0.8 L1 +
    0.2 D-SSIM): dL/du = (1/N) sum_p sign(r_p) c da_p/du over the Gaussian's footprint.
    - A Gaussian of about one pixel at the level (the size 3DGS densifies down to; the
      rasterizer's 0.3 px^2 blur keeps it there): the sum over its few pixels does not depend on
      the level, so |dL/du| ~ 1/N and the NDC norm ~ (W/2)/N = 1/(2H): s times its full-size
      value at H / s. This is the full bench's 720 / H rule of the threshold
      (``bench/presets.py``, FULL_GROW_GRAD2D).
    - A Gaussian of many pixels: u' = u / s, its footprint A / s^2 pixels, da/du' = s da/du, so
      dL/du' = s dL/du and W'/2 = W/(2 s): the NDC norm is the same at every level.
    The gradient of a Gaussian thus grows by a factor between 1 and s at level s (measured on
    beer --data-factor 4 after 600 steps: median 1.38 at s = 2 and 1.87 at s = 4, docs/training.md).
    Dividing by s holds the pixel-sized Gaussians' statistic, the one that decides when
    densification stops, to its full-size value: a level densifies down to its own pixel and not
    below (detail it cannot show), and never more than full size would."""
    grads = pixel_grads.detach() if pixel_grads.requires_grad else pixel_grads  # no operator where none is needed
    if grads.dtype != torch.float32:
        grads = grads.to(torch.float32)
    return (grads * _ndc_scale(grads.device, width, height, n_cameras, downscale, reference_height)).norm(dim=-1)


@functools.lru_cache(maxsize=64)
def _ndc_scale(device: torch.device, width: int, height: int, n_cameras: int, downscale: int,
               reference_height: int | None) -> Tensor:
    """The [2] float32 factors of :func:`ndc_gradient_norms`, made once per device and view size
    (a run has a few: its levels and batch sizes), so a step dispatches no operator for them.
    Filled on the device, not made there from a list: on a GPU that is a copy from the host, which
    torch makes wait for every kernel queued before it. Never written to after it is made."""
    scale = torch.empty(2, dtype=torch.float32, device=device)
    scale[0], scale[1] = width / 2.0, height / 2.0
    scale = scale * float(n_cameras)
    if downscale != 1:
        scale = scale / float(downscale)
    if reference_height is not None:
        scale = scale * (float(height * downscale) / float(reference_height))
    return scale


def grow_masks(
    avg_grad: Tensor, log_scales: Tensor, grad_threshold: float, clone_max_scale: float,
    avg_abs: Tensor | None = None, abs_threshold: float = 0.0,
) -> tuple[Tensor, Tensor]:
    """3DGS growth decisions: (clone [N], split [N]) bool masks.

    High gradient (> threshold) and small (max scale <= clone_max_scale) -> clone; high and
    large -> split. With ``avg_abs`` (AbsGS's statistic), a large Gaussian whose absolute sums
    exceed ``abs_threshold`` is split too: over texture its pixels pull it in opposite directions
    and the summed gradient cancels, the absolute sums do not. Clones stay 3DGS's.
    """
    high = avg_grad > grad_threshold
    small = max_world_scale(log_scales) <= clone_max_scale
    split = high & ~small
    if avg_abs is not None:
        split |= (avg_abs > abs_threshold) & ~small
    return high & small, split


def limit_growth(clone: Tensor, split: Tensor, score: Tensor, room: int) -> tuple[Tensor, Tensor]:
    """Keep at most ``room`` growth candidates (each clone or split adds one Gaussian).

    When the cap binds, the candidates with the highest ``score`` (the gradient statistic) win;
    ties keep index order (stable sort), so the choice is deterministic.
    """
    candidates = clone | split
    if int(candidates.sum()) <= room:
        return clone, split
    idx = torch.where(candidates)[0]
    order = torch.sort(score[idx], descending=True, stable=True).indices
    keep = torch.zeros_like(candidates)
    keep[idx[order[:room]]] = True
    return clone & keep, split & keep


def prune_masks(
    opacity_logits: Tensor, log_scales: Tensor, min_opacity: float, max_world_size: float | None
) -> tuple[Tensor, Tensor | None]:
    """Gaussians to prune: (sigmoid(opacity) < min_opacity or max scale > max_world_size, the
    latter alone; None without a size limit)."""
    mask = torch.sigmoid(opacity_logits.flatten()) < min_opacity
    if max_world_size is None:
        return mask, None
    too_big = max_world_scale(log_scales) > max_world_size
    return mask | too_big, too_big


ScoreWithout = Callable[[Tensor], Sequence[float]]
"""The end-of-run cut's check: given rows to leave out ([N] bool), the PSNR (dB) of each checked
training view rendered without them (the pipeline renders; the same views in the same order at
every call)."""


# ---------------------------------------------------------------------------- strategy
@dataclass
class DefaultStrategy(Strategy):
    """3DGS adaptive density control: clone, split, prune, periodic opacity reset."""

    MORE_GAUSSIANS: ClassVar[str] = "a lower --strategy.grow-grad2d"

    prune_opa: float = 0.005
    """Prune Gaussians whose opacity is below this value."""
    grow_grad2d: float = 0.0002
    """Clone/split Gaussians whose view-averaged NDC gradient norm exceeds this value."""
    grow_scale3d: float = 0.01
    """Clone when the largest scale is at most this fraction of the scene extent, else split."""
    prune_scale3d: float = 0.1
    """After the first opacity reset, prune Gaussians larger than this fraction of the extent."""
    reset_opacity: float = 0.01
    """Opacity reset value (opacities are clamped to at most this)."""
    split_scale_factor: float = 1.6
    """Split children get the parent's scales divided by this factor."""
    grow_grad2d_height: int | None = None
    """The training-image height (pixels) at which grow_grad2d holds: each view's statistic is
    scaled by its height H over this one, so the threshold is grow_grad2d x this / H (3DGS's 0.0002
    at 720 pixels high, REFERENCE_HEIGHT, is 0.0008 at 180). None: grow_grad2d as given at every
    height (the default: at 720 it cost 0.23 dB and 0.02 LPIPS on beer at --data-factor 4,
    docs/strategies.md)."""
    absgrad: bool = False
    """Grow by AbsGS's statistic: per view, the norm of the sums over the pixels of each pixel's
    |dL/dx| and |dL/dy| instead of the norm of the summed gradient, so that a Gaussian whose pixels
    pull it apart (a blur over texture) grows too. The sums are several times the summed gradient:
    pair it with a higher grow_grad2d. At 0.001 it grew 18% fewer Gaussians than 0.0002 without it
    on beer (--data-factor 4) at the same PSNR and LPIPS, and 69% more on fox at +1.07 dB and
    -0.048 LPIPS: the count follows the scene (docs/strategies.md)."""
    split_absgrad2d: float | None = None
    """AbsGS's split rule beside 3DGS's: a Gaussian too large to clone is also split when the mean
    over its views of the norm of the sums of each pixel's |dL/dx| and |dL/dy| (NDC, as
    grow_grad2d's statistic) exceeds this. The summed gradient of a blur over texture cancels and
    never reaches grow_grad2d; these sums do. Clones stay 3DGS's (absgrad grows clones by the sums
    too; the two do not go together). None: off (docs/strategies.md)."""
    prune_weight_share: float = 0.0
    """At each refinement (and once more at the end of growth), prune the least significant
    Gaussians that together painted at most this share of the compositing weight of the window's
    training views (the renderer sums it as it draws them; docs/strategies.md). 0: off (the
    default: every share measured cost more than 0.1 dB). Off too when cap_max is a count (the
    user's count) and on a renderer without the sums (gsplat's)."""

    final_weight_share: float = 0.003
    """After the last step, before the final evaluation, remove the Gaussians of least weight x
    peak (their compositing weight in the training view that needs them most times their largest
    weight at one pixel, model/significance.visibility_cut_order) that together painted at most
    this share of the training views' compositing weight,
    and every Gaussian that no training view draws (summed by the training renders of the run's last
    whole epoch, engine/final_weights.py, or, where the run has none after growth, one pass over the
    training views; the count and why in one line); with final_cut_tolerance, the first share the check tries. Measured on the
    re-posed beer and builtin:farside in docs/strategies.md. 0: off. Off too when cap_max is a count
    (the user's), on gsplat's kernels (no weight sums) and for a dynamic model."""
    settled_cut_iter: int | None = None
    """After this many steps the checked cut (final_weight_share, settled_cut_tolerance) also runs
    once, after growth has stopped, so that the rest of the run trains only the Gaussians it keeps
    and the cut after the last step judges a set that has had those steps to take up the slack.
    None: settled_cut_frac of the run, filled by setup(schedule) like the refine fields (a strategy
    used without a schedule makes no such cut). 0: the cut after the last step only. No cut here
    unless it falls after refine_stop_iter and before the last step, nor when final_weight_share is
    0 (docs/strategies.md)."""
    settled_cut_frac: float = 0.8
    """Where settled_cut_iter falls when left unset, as a share of the run's steps. Growth stops at
    half the run (refine_stop_frac); the later the cut, the more settled the set it judges and the
    less its cut costs: on beer (six seeds, paired with the same runs uncut) after 57% of the run
    +0.0129 LPIPS, 67% +0.0056, 80% +0.0023 (docs/strategies.md). A config saved before this field
    loads with 2/3, as it trained."""
    settled_cut_tolerance: float | None = 0.3
    """The settled cut's check: as final_cut_tolerance (dB the checked training views may lose),
    for the cut that training follows. Its check reads the loss at once, and the steps after it
    win part of it back, so it may take more than the end-of-run cut, after which nothing trains:
    on beer within 0.3 dB at 80% of the run, 47.5% of the count at -0.03 dB and +0.0041 LPIPS
    against 53.3% at -0.01 dB and +0.0023 within 0.1 (docs/strategies.md). None: final_cut_tolerance
    (a config saved before this field loads with None, as it trained)."""
    final_cut_tolerance: float = 0.1
    """The cut is checked: the rows no training view draws go, then the cut at final_weight_share
    and at each larger share of CHECKED_SHARES in turn while the training views lose at most this
    PSNR (dB) against the whole set: per view d_v = PSNR before - PSNR after, over CHECK_VIEWS views
    evenly spread, mean(d) + sd(d) / sqrt(k) <= this. Training views need none held out, and they
    err on keeping: a row that paints only what the run overfit costs PSNR on them and none on new
    views. One render of each checked view for the whole set and for each share tried. 0: the cut
    at final_weight_share, unchecked (docs/strategies.md)."""

    def __post_init__(self) -> None:
        super().__post_init__()
        if not 0.0 < self.reset_opacity < 1.0:
            raise StrategyError(f"reset_opacity must be in (0, 1), got {self.reset_opacity}")
        if self.split_scale_factor <= 0.0:
            raise StrategyError(f"split_scale_factor must be positive, got {self.split_scale_factor}")
        if self.grow_grad2d_height is not None and self.grow_grad2d_height <= 0:
            raise StrategyError(f"grow_grad2d_height must be positive or None, got {self.grow_grad2d_height}")
        if not 0.0 <= self.prune_weight_share < 1.0:
            raise StrategyError(f"prune_weight_share must be in [0, 1), got {self.prune_weight_share}")
        if not 0.0 <= self.final_weight_share < 1.0:
            raise StrategyError(f"final_weight_share must be in [0, 1), got {self.final_weight_share}")
        if not self.final_cut_tolerance >= 0.0:
            raise StrategyError(f"final_cut_tolerance must be >= 0 dB, got {self.final_cut_tolerance}")
        if self.settled_cut_iter is not None and self.settled_cut_iter < 0:
            raise StrategyError(f"settled_cut_iter must be >= 0 or None, got {self.settled_cut_iter}")
        if not 0.0 < self.settled_cut_frac < 1.0:
            raise StrategyError(f"settled_cut_frac must be in (0, 1), got {self.settled_cut_frac}")
        if self.settled_cut_tolerance is not None and not self.settled_cut_tolerance >= 0.0:
            raise StrategyError(f"settled_cut_tolerance must be >= 0 dB or None, got {self.settled_cut_tolerance}")
        if self.split_absgrad2d is not None and not self.split_absgrad2d > 0.0:
            raise StrategyError(f"split_absgrad2d must be positive or None, got {self.split_absgrad2d}")
        if self.split_absgrad2d is not None and self.absgrad:
            raise StrategyError("split_absgrad2d splits by the absolute sums beside the summed gradient; with absgrad "
                                "every growth reads the sums already: set one of the two")

    # ------------------------------------------------------------------ significance prune
    def prunes_by_significance(self) -> bool:
        """Whether the significance prune runs: a share above 0 and no count set by the user."""
        return self.prune_weight_share > 0.0 and not isinstance(self.cap_max, int)

    def requirements(self) -> frozenset[str]:
        required = super().requirements()
        if self.absgrad or self.splits_by_absolute_sums():
            required |= {ABSOLUTE_GRADIENT}
        return required | {VISIBILITY_STATS} if self.prunes_by_significance() else required

    def splits_by_absolute_sums(self) -> bool:
        """Whether the absolute sums are kept beside the summed gradient, for split_absgrad2d."""
        return self.split_absgrad2d is not None

    def without_visibility(self) -> "DefaultStrategy | None":
        """This strategy for a renderer that cannot sum the compositing weights: the significance
        prune off (None where the strategy needs the sums for more than that: occlusion-aware splitting)."""
        without = dataclasses.replace(self, prune_weight_share=0.0)
        return None if VISIBILITY_STATS in without.requirements() else without

    def initialize_state(self, scene_scale: float = 1.0, scene_center: Tensor | None = None) -> dict[str, Any]:
        state = super().initialize_state(scene_scale, scene_center)
        state.update({SIGNIFICANCE_PRUNED: 0, SIGNIFICANCE_NOTE: ""})
        return state

    def _significance_mask(self, state: dict[str, Any], step: int, window: int) -> Tensor | None:
        """The rows the significance prune removes at ``step`` (the end of a window of ``window``
        steps), or None where it does not judge."""
        stats = state["stats"]
        if (not self.prunes_by_significance() or WEIGHT not in stats
                or window_follows_reset(step, window, self.reset_every)):
            return None
        return least_significant(stats[WEIGHT], stats[WEIGHT_VIEWS], self.prune_weight_share,
                                 cut_order(stats[WEIGHT], stats[WEIGHT_PEAK]))

    def count_decision(self, state: dict[str, Any]) -> str:
        return super().count_decision(state) or state.get(SIGNIFICANCE_NOTE, "")

    def cut_lines(self, state: dict[str, Any]) -> list[str]:
        return list(state.get(CUT_NOTES, ()))

    def schedule_defaults(self, schedule: Schedule) -> dict[str, int]:
        return {**super().schedule_defaults(schedule),
                "settled_cut_iter": round(self.settled_cut_frac * schedule.max_steps)}

    def final_cut_share(self) -> float:
        return 0.0 if isinstance(self.cap_max, int) else self.final_weight_share

    def settled_cut_step(self, max_steps: int) -> int | None:
        step = self.settled_cut_iter
        if (self.final_cut_share() <= 0.0 or not step or self.refine_stop_iter is None
                or not self.refine_stop_iter < step < max_steps - 1):
            return None
        return step

    def final_cut(self, params: Params, optimizers: Optimizers, state: dict[str, Any], visibility: Tensor,
                  step: int, score_without: ScoreWithout | None = None, last: bool = True) -> int:
        share = self.final_cut_share()
        if share <= 0.0 or num_gaussians(params) == 0:
            return 0
        before = num_gaussians(params)
        # Every row is judged: over every training view, a row that none draws paints nothing that
        # training sees (outside every view, or behind what stops the compositing) and is cut first,
        # for free. (The prune while growing judges only the rows its window's few views drew.)
        weights, judged = visibility[:, 0], torch.ones_like(visibility[:, 0])
        order = visibility_cut_order(visibility)
        checked = ""
        tolerance, flag = self._cut_tolerance(last)
        if tolerance > 0.0 and score_without is not None:
            cut, share, checked = self._checked_cut(weights, judged, order, visibility[:, 1] <= 0.0, share,
                                                    score_without, tolerance, flag)
        else:
            cut = least_significant(weights, judged, share, order)
        n = row_ops.remove(params, optimizers, state["stats"], cut)
        when = f"after the last step ({step + 1})" if last else f"after step {step + 1}, for the rest of the run"
        off = ("--strategy.final-weight-share 0 keeps them" if last else
               "--strategy.settled-cut-iter 0 cuts after the last step only")
        which = (f"the {n:,} of least weight x peak, which together painted at most {share:.1%} of the training "
                 f"views' blend weight, were cut" if share > 0.0 else f"the {n:,} that no training view draws were cut")
        state[SIGNIFICANCE_NOTE] = (
            f"count: {before - n:,} of {before:,} Gaussians kept {when}: {which}{checked} ({off})")
        state.setdefault(CUT_NOTES, []).append(state[SIGNIFICANCE_NOTE])
        return n

    def _cut_tolerance(self, last: bool) -> tuple[float, str]:
        """The check's tolerance (dB) of the cut after the last step (``last``) or of the settled
        cut, and the flag that sets it."""
        if last or self.settled_cut_tolerance is None:
            return self.final_cut_tolerance, "--strategy.final-cut-tolerance"
        return self.settled_cut_tolerance, "--strategy.settled-cut-tolerance"

    def _checked_cut(self, weights: Tensor, judged: Tensor, order: Tensor, undrawn: Tensor, share: float,
                     score_without: ScoreWithout, tolerance: float, flag: str) -> tuple[Tensor, float, str]:
        """The largest of ``share`` and the larger CHECKED_SHARES whose rows the checked training
        views miss by at most ``tolerance`` (dB): the paired deficit (count_rule.paired_deficit)
        against the whole set. The cuts are nested (the rows no view draws, which cost nothing, then
        each share's), so the first that costs more ends the search. Returns (the rows to cut, their
        share, 0 for the undrawn rows alone; the words the count line adds)."""
        base = score_without(torch.zeros_like(undrawn))
        cut, kept_share, kept_deficit, refused = undrawn, 0.0, None, "; the largest share tried"
        for larger in [share] + [q for q in CHECKED_SHARES if q > share]:
            more = least_significant(weights, judged, larger, order)
            if int(more.sum()) == int(cut.sum()):
                continue  # no row more: nothing to check
            deficit = paired_deficit(base, score_without(more))
            if not deficit <= tolerance:  # a NaN deficit is refused too
                refused = f"; {larger:.1%} would lose {deficit:.2f} dB"
                break
            cut, kept_share, kept_deficit = more, larger, deficit
        lost = "nothing" if kept_deficit is None else f"{kept_deficit:.2f} dB"
        return cut, kept_share, (f"; the {len(base)} training views checked lose {lost} (at most "
                                 f"{tolerance:g}, {flag}){refused}")

    # ------------------------------------------------------------------ hooks for subclasses
    def size_prune_factor(self, step: int) -> float:
        """World-size prune threshold as a fraction of the extent (Seeding relaxes it)."""
        return self.prune_scale3d

    def extra_prune(self, params: Params, state: dict[str, Any], step: int) -> tuple[Tensor | None, dict[str, int]]:
        """More rows to prune at a refinement step, beside the opacity and size criteria.

        Returns (mask [N] bool or None for none, counts to report). Default: the significance
        prune's rows. Overrides call super() first and OR their mask in.
        """
        if not self.prunes_by_significance():
            return None, {}
        mask = self._significance_mask(state, step, self.refine_every)
        if mask is None:
            return None, {"pruned_significance": 0}
        n = int(mask.sum())
        state[SIGNIFICANCE_PRUNED] = state.get(SIGNIFICANCE_PRUNED, 0) + n
        return mask, {"pruned_significance": n}

    def observe(self, params: Params, state: dict[str, Any], view: ViewObservation) -> dict[str, int]:
        """Read one of this step's views before the Gaussian set changes (inside the window).

        Default accumulates the gradient statistic; subclasses extend (super() first).
        """
        return {"nonfinite_grads": self._update_stats(params, state, view)}

    def explore(self, ctx: StepContext) -> dict[str, int]:
        """Exploration operators run here on every step, after densification and before the
        opacity reset (Default: none). Overrides call super() first."""
        return {}

    # ------------------------------------------------------------------ contract
    def step_pre_backward(
        self, params: Params, optimizers: Optimizers, state: dict[str, Any], step: int, view: ViewObservation
    ) -> None:
        view.keep_gradient(type(self).__name__)

    def post_backward(self, ctx: StepContext) -> dict[str, int]:
        params, optimizers, state, step = ctx.params, ctx.optimizers, ctx.state, ctx.step
        counts = {"cloned": 0, "split": 0, "pruned": 0, "opacity_reset": 0, "nonfinite_grads": 0}
        in_window = step < self.refine_stop_iter
        if in_window:
            for view in ctx.views:
                for key, value in self.observe(params, state, view).items():
                    counts[key] = counts.get(key, 0) + value
            if step > self.refine_start_iter and step % self.refine_every == 0:
                counts["cloned"], counts["split"] = self._grow(params, optimizers, state, ctx.generator)
                counts.update(self._prune(params, optimizers, state, step))
                for key in GRAD_STATS + ABS_GRAD_STATS + WEIGHT_STATS:
                    if key in state["stats"]:
                        state["stats"][key].zero_()
        elif step == self.refine_stop_iter and self.prunes_by_significance():
            counts.update(self._last_significance_prune(params, optimizers, state, step))
        counts.update(self.explore(ctx))
        if in_window and step > 0 and step % self.reset_every == 0:
            row_ops.reset_opacity(params, optimizers, self.reset_opacity)
            counts["opacity_reset"] = 1
        return counts

    # ------------------------------------------------------------------ steps
    def _last_significance_prune(self, params: Params, optimizers: Optimizers, state: dict[str, Any],
                                 step: int) -> dict[str, int]:
        """At the end of growth: judge the views since the last refinement once more (the rows its
        growth made were not judged yet), and write the line that says the count and why."""
        last = self.last_refinement()
        mask = self._significance_mask(state, step, step - last if last > 0 else step)
        n = row_ops.remove(params, optimizers, state["stats"], mask) if mask is not None and num_gaussians(params) else 0
        state[SIGNIFICANCE_PRUNED] = state.get(SIGNIFICANCE_PRUNED, 0) + n
        state[SIGNIFICANCE_NOTE] = (
            f"count: {num_gaussians(params):,} Gaussians at the end of growth (step {step}): the refinements "
            f"pruned the least significant Gaussians, those that together painted at most "
            f"{self.prune_weight_share:.1%} of the training views' blend weight ({state[SIGNIFICANCE_PRUNED]:,} "
            f"pruned so; --strategy.prune-weight-share 0 turns it off)")
        for key in WEIGHT_STATS:
            state["stats"].pop(key, None)
        return {"pruned": n, "pruned_significance": n}

    def _update_stats(self, params: Params, state: dict[str, Any], view: ViewObservation) -> int | Tensor:
        n = num_gaussians(params)
        if n == 0:
            return 0
        view.check_rows(n)
        grad = view.screen_gradient(absolute=self.absgrad)
        if grad is None:
            return 0  # no gradient reached the 2D means this step (nothing visible)
        if tuple(grad.shape) != (n, 2):
            raise StrategyError(
                f"the view's 2D-mean gradient has shape {tuple(grad.shape)} but there are {n} Gaussians: "
                f"the observation must come from rendering the current Gaussian set"
            )
        visible = view.visible()
        if self.prunes_by_significance() and view.visibility is not None:
            accumulate_weights(state["stats"], view.visibility, visible)
        skipped = accumulate_grad_stats(
            state["stats"], grad, visible, view.width, view.height, view.n_cameras, view.downscale,
            self.grow_grad2d_height,
        )
        if self.splits_by_absolute_sums():
            sums = view.screen_gradient(absolute=True)
            if sums is not None:
                accumulate_grad_stats(state["stats"], sums, visible, view.width, view.height, view.n_cameras,
                                      view.downscale, self.grow_grad2d_height, names=ABS_GRAD_STATS)
        return skipped

    def growth(self, params: Params, state: dict[str, Any]) -> tuple[Tensor, Tensor]:
        """This refinement's (clone [N], split [N]) masks: the 3DGS rule on the gradient statistic
        (with split_absgrad2d, AbsGS's split by the absolute sums too), limited by cap_max. A
        densifier that chooses otherwise overrides this; :meth:`_grow` applies it."""
        stats = state["stats"]
        avg_grad = stats["grad2d"] / stats["count"].clamp_min(1.0)
        total, count = ABS_GRAD_STATS
        avg_abs = None
        if self.splits_by_absolute_sums() and total in stats:
            avg_abs = stats[total] / stats[count].clamp_min(1.0)
        clone, split = grow_masks(
            avg_grad, params["scales"].detach(), self.grow_grad2d, self.grow_scale3d * state["scene_scale"],
            avg_abs, self.split_absgrad2d or 0.0,
        )
        return limit_growth(clone, split, avg_grad, self.room(num_gaussians(params)))

    def _grow(
        self, params: Params, optimizers: Optimizers, state: dict[str, Any], generator: torch.Generator | None
    ) -> tuple[int, int]:
        stats = state["stats"]
        if "grad2d" not in stats or num_gaussians(params) == 0:
            return 0, 0
        clone, split = self.growth(params, state)
        n_cloned = row_ops.duplicate(params, optimizers, stats, clone)
        # Clones are appended at the end and are never split in the same step.
        split = torch.cat([split, torch.zeros(n_cloned, dtype=torch.bool, device=split.device)])
        n_split = 0
        if bool(split.any()):
            gen = require_generator(generator, f"{type(self).__name__} (split)")
            n_split = row_ops.split(params, optimizers, stats, split, gen, self.split_scale_factor)
        return n_cloned, n_split

    def _prune(self, params: Params, optimizers: Optimizers, state: dict[str, Any], step: int) -> dict[str, int]:
        if num_gaussians(params) == 0:
            return {"pruned": 0}
        # 3DGS turns the world-size criterion on only once the first opacity reset has happened.
        max_size = None
        if step > self.reset_every:
            max_size = self.size_prune_factor(step) * state["scene_scale"]
        mask, too_big = prune_masks(params["opacities"].detach(), params["scales"].detach(), self.prune_opa, max_size)
        extra, counts = self.extra_prune(params, state, step)
        if too_big is not None:
            # said apart: a row over the world-size limit paints a large part of any view that sees
            # it, so even a few removed set the renders back on purpose (collapse.deliberate_setback)
            counts = {**counts, "pruned_too_big": int(too_big.sum())}
        if extra is not None:
            mask = mask | extra
        return {**counts, "pruned": row_ops.remove(params, optimizers, state["stats"], mask)}
