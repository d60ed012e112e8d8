"""Random Seeding (far side): new Gaussians uniform in the box of the current centres.

At every seeding step ``n_seed`` Gaussians are placed uniformly in the axis-aligned bounding box
of the current centres (a per-axis quantile box is an option). With r the distance of a point
from the scene centre, their attributes follow the authors' reference implementation:

    sh0     from a uniformly random RGB colour, higher SH = 0
    scale   isotropic, s_new = r_new * mean_i( mean_axis(s_i) / r_i )   over existing Gaussians
    opacity 0.2 + 0.5 * r_new / max(r_new over this batch)
    quat    uniform random unit quaternion

While seeding is active the world-size prune threshold is relaxed (0.1 -> 10 x extent) so far
seeds survive.

Seed probation: a seed that lands in empty space fades (its colour cannot match what lies
behind it in every view), but joint optimisation lets the Gaussians behind it compensate, so it
settles at opacity 0.005-0.05 instead of crossing the normal prune threshold (0.005). At every
refinement step, outside a grace period after an opacity reset, seeds and their descendants
below ``prune_opa`` are therefore pruned as well: a seed that has not grown opaque has
found nothing to explain.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Literal

import torch
from torch import Tensor

from ..rasterizer.sh import rgb_to_sh0
from . import row_ops
from .errors import StrategyError
from .exploration import ExplorationStrategy
from .geometry import random_unit_quats
from .observation import ViewObservation
from .operator_contract import Operator
from .row_ops import Optimizers, Params, num_gaussians

if TYPE_CHECKING:
    from .base import StepContext
    from .default import DefaultStrategy

_EPS = 1e-12

SEED_FLAG = "seed"
"""Per-Gaussian statistic: 1 for seeds (and their descendants), 0 otherwise."""
SEED_SEEN = "seed_seen"
"""Per-Gaussian statistic: number of training views in which the row was visible since seeding."""


def seed_box(means: Tensor, mode: str = "aabb", quantile: float = 0.01, center: Tensor | None = None,
             extent: float = 1.0) -> tuple[Tensor, Tensor] | None:
    """Box of the finite centres: (lo [3], hi [3]); None when there is no finite centre.

    mode 'aabb' is the paper's rule (min/max); 'robust' uses the per-axis ``quantile`` and
    ``1 - quantile`` so a few outliers do not inflate the box; 'cameras' is the cube
    ``center +- extent`` (the cameras' centre and the scene extent, 1.1 x the farthest camera's
    distance from it), where the released code of the paper seeds.
    """
    finite = means[torch.isfinite(means).all(dim=-1)]
    if finite.shape[0] == 0:
        return None
    if mode == "cameras":
        if center is None:
            raise StrategyError("seed box mode 'cameras' needs the cameras' centre")
        c = center.to(dtype=finite.dtype, device=finite.device)
        return c - float(extent), c + float(extent)
    if mode == "aabb":
        return finite.min(dim=0).values, finite.max(dim=0).values
    if mode == "robust":
        q = torch.tensor([quantile, 1.0 - quantile], dtype=finite.dtype, device=finite.device)
        lo_hi = torch.quantile(finite, q, dim=0)
        return lo_hi[0], lo_hi[1]
    raise StrategyError(f"seed box mode must be 'aabb', 'robust' or 'cameras', got '{mode}'")


def seed_rows(
    means: Tensor,
    log_scales: Tensor,
    n_seed: int,
    generator: torch.Generator,
    scene_center: Tensor,
    sh_rest: int,
    *,
    box: str = "aabb",
    box_quantile: float = 0.01,
    extent: float = 1.0,
    opacity_base: float = 0.2,
    opacity_gain: float = 0.5,
    min_scale: float = 1e-7,
) -> dict[str, Tensor] | None:
    """Raw parameter rows of ``n_seed`` seeds; None when no box exists (no finite centre).

    means, log_scales: [N, 3] existing Gaussians; scene_center: [3]; sh_rest: K - 1 higher SH
    coefficients. Returns {means [S,3], scales [S,3], quats [S,4], opacities [S], sh0 [S,1,3],
    shN [S,sh_rest,3]}. A zero-volume box (e.g. one Gaussian, coplanar centres) is kept as is:
    seeds lie in it. ``min_scale`` floors the scale of a seed that lands on the centre; ``extent``
    is the half-side of the 'cameras' box.
    """
    bounds = seed_box(means.detach(), box, box_quantile, scene_center, extent)
    if bounds is None or n_seed <= 0:
        return None
    lo, hi = bounds
    dtype = means.dtype
    center = scene_center.to(dtype=dtype, device=means.device)
    u = torch.rand(n_seed, 3, generator=generator, dtype=dtype, device=generator.device).to(means.device)
    positions = lo + u * (hi - lo)

    # Scale per unit distance from the centre, averaged over existing Gaussians whose distance
    # and scale are usable (r_i > 0, finite); if none is, fall back to their mean scale.
    r_old = (means.detach() - center).norm(dim=-1)
    s_old = torch.exp(log_scales.detach()).mean(dim=-1)
    usable = torch.isfinite(r_old) & torch.isfinite(s_old) & (r_old > _EPS)
    r_new = (positions - center).norm(dim=-1)
    if bool(usable.any()):
        s_new = r_new * (s_old[usable] / r_old[usable]).mean()
    else:
        finite_s = s_old[torch.isfinite(s_old)]
        fallback = finite_s.mean() if finite_s.numel() else torch.tensor(1.0, dtype=dtype, device=means.device)
        s_new = fallback.expand(n_seed)
    s_new = s_new.clamp_min(min_scale)

    r_max = r_new.max()
    ratio = r_new / r_max if float(r_max) > _EPS else torch.zeros_like(r_new)
    opacity = (opacity_base + opacity_gain * ratio).clamp(1e-6, 1.0 - 1e-6)

    rgb = torch.rand(n_seed, 3, generator=generator, dtype=dtype, device=generator.device).to(means.device)
    return {
        "means": positions,
        "scales": torch.log(s_new).unsqueeze(-1).expand(n_seed, 3).clone(),
        "quats": random_unit_quats(n_seed, generator, dtype),
        "opacities": torch.logit(opacity),
        "sh0": rgb_to_sh0(rgb),
        "shN": torch.zeros(n_seed, sh_rest, 3, dtype=dtype, device=means.device),
    }


def add_seeds(params: Params, optimizers: Optimizers, stats: dict[str, Tensor], rows: dict[str, Tensor]) -> int:
    """Append seed ``rows`` (raw, every parameter key) flagged as seeds (``SEED_FLAG``, with
    ``SEED_SEEN`` counting the views that see them from now on). Returns the count added."""
    n_before = num_gaussians(params)
    for key in (SEED_FLAG, SEED_SEEN):
        stats.setdefault(key, torch.zeros(n_before, device=params["means"].device))
    added = row_ops.append(params, optimizers, stats, rows)
    stats[SEED_FLAG][n_before:] = 1.0
    return added


@dataclass
class RandomSeeding(Operator):
    """Random Seeding: ``n_seed`` new Gaussians in the seed box every ``every`` steps while the
    densification window is open, with the relaxed world-size prune and seed probation."""

    COUNTS = ("seeded", "seeds_pruned")
    BUDGET_FIELDS = {"n_seed": "n_seed", "every": "seed_every"}

    n_seed: int | None = None
    """Seeds added per seeding step (0 disables). None: from the strategy's budget (paper: 20)."""
    every: int | None = None
    """Seeding interval in steps. None: from the strategy's budget (paper: the densification interval)."""
    box_mode: Literal["aabb", "robust", "cameras"] = "aabb"
    """Seed box: 'aabb' of all centres (the paper's text), 'robust' per-axis quantiles, or 'cameras':
    the cube of half-side the scene extent around the cameras' centre (the paper's released code)."""
    box_quantile: float = 0.01
    """Quantile trimmed from each side of each axis in the 'robust' box."""
    opacity_base: float = 0.2
    """Seed opacity = base + gain * r / max r (r: distance from the scene centre, over the batch)."""
    opacity_gain: float = 0.5
    """The gain of that formula: opacity added for the seed farthest from the centre."""
    prune_scale3d: float = 10.0
    """While seeding is active, prune only Gaussians larger than this fraction of the extent."""
    min_scale: float = 1e-6
    """Smallest seed scale, as a fraction of the scene extent (guards r = 0)."""
    prune_opa: float = 0.05
    """Seed probation: at refinement steps, prune seeds (and descendants) whose opacity is below
    this; faded seeds otherwise linger above Default's prune_opa. 0 disables (normal pruning only)."""
    grace: int | None = None
    """Steps after an opacity reset before seeds are judged again, so useful ones can climb back
    from the reset value. None: half the reset interval."""

    def __post_init__(self) -> None:
        where = type(self).__name__
        for name, low, note in (("n_seed", 0, " (0 disables seeding)"), ("every", 1, "")):
            value = getattr(self, name)
            if value is not None and value < low:
                raise StrategyError(f"{where}.{name} must be >= {low}{note}, got {value}")
        if not 0.0 <= self.box_quantile < 0.5:
            raise StrategyError(f"{where}.box_quantile must be in [0, 0.5), got {self.box_quantile}")
        if not 0.0 < self.opacity_base + self.opacity_gain < 1.0 or self.opacity_base <= 0:
            raise StrategyError(f"{where}: seed opacities base and base + gain must lie in (0, 1)")
        if not 0.0 <= self.prune_opa < 1.0:
            raise StrategyError(f"{where}.prune_opa must be in [0, 1), got {self.prune_opa}")
        if self.grace is not None and self.grace < 0:
            raise StrategyError(f"{where}.grace must be >= 0, got {self.grace}")

    def active(self, owner: DefaultStrategy, step: int) -> bool:
        return bool(self.n_seed) and step < owner.refine_stop_iter

    def size_prune_factor(self, owner: DefaultStrategy, step: int) -> float | None:
        return self.prune_scale3d if self.active(owner, step) else None

    def judged_at(self, owner: DefaultStrategy, step: int) -> bool:
        """Whether a refinement at ``step`` applies seed probation: no opacity reset yet, or the
        last one (at a multiple of reset_every before this step) at least the grace period ago."""
        reset_every = owner.reset_every
        last_reset = (step - 1) // reset_every * reset_every  # this step's own reset comes after its prune
        if last_reset <= 0:
            return True
        grace = self.grace if self.grace is not None else reset_every // 2
        return step - last_reset >= grace

    def extra_prune(self, owner: DefaultStrategy, params: Params, state: dict[str, Any],
                    step: int) -> tuple[Tensor | None, dict[str, int]]:
        flag = state["stats"].get(SEED_FLAG)
        if flag is None or self.prune_opa <= 0.0 or not self.judged_at(owner, step):
            return None, {"seeds_pruned": 0}
        faded = (flag > 0) & (torch.sigmoid(params["opacities"].detach().flatten()) < self.prune_opa)
        return faded, {"seeds_pruned": int(faded.sum())}

    def observe(self, owner: DefaultStrategy, params: Params, state: dict[str, Any],
                view: ViewObservation) -> dict[str, int]:
        stats = state["stats"]
        if SEED_SEEN in stats and num_gaussians(params) > 0:
            stats[SEED_SEEN] += view.visible().to(stats[SEED_SEEN].dtype)
        return {}

    def explore(self, owner: DefaultStrategy, ctx: StepContext) -> dict[str, int]:
        seeded = 0
        if self.active(owner, ctx.step) and ctx.step > owner.refine_start_iter and ctx.step % self.every == 0:
            seeded = self.seed(owner, ctx.params, ctx.optimizers, ctx.state, ctx.rng("seeding"))
        return {"seeded": seeded}

    def exploration_summary(self, state: dict[str, Any]) -> dict[str, int]:
        """Current totals (not events): ``seeds_alive``, seeds and their descendants still in
        the set, and ``seeds_unseen``, those that no training view has seen since they were
        added (no gradient ever reaches them, so only pruning or the end of the run removes them).
        """
        flag = state["stats"].get(SEED_FLAG)
        if flag is None:
            return {"seeds_alive": 0, "seeds_unseen": 0}
        alive = flag > 0
        return {
            "seeds_alive": int(alive.sum()),
            "seeds_unseen": int((alive & (state["stats"][SEED_SEEN] == 0)).sum()),
        }

    def new_seed_rows(self, params: Params, state: dict[str, Any], n: int, generator: torch.Generator
                      ) -> dict[str, Tensor] | None:
        """Raw rows of ``n`` new seeds (None: nowhere to seed): uniform in the box of the centres.
        Other placements (guided seeding) override this; flags and probation stay the same."""
        return self.box_seed_rows(params, state, n, generator)

    def box_seed_rows(self, params: Params, state: dict[str, Any], n: int, generator: torch.Generator
                      ) -> dict[str, Tensor] | None:
        """Raw rows of ``n`` seeds uniform in the seed box (``box_mode``), the paper's placement,
        whatever :meth:`new_seed_rows` a subclass chose (MCMC-explore draws from both)."""
        return seed_rows(
            params["means"],
            params["scales"],
            n,
            generator,
            state["scene_center"],
            params["shN"].shape[1],
            box=self.box_mode,
            box_quantile=self.box_quantile,
            extent=state["scene_scale"],
            opacity_base=self.opacity_base,
            opacity_gain=self.opacity_gain,
            min_scale=self.min_scale * state["scene_scale"],
        )

    def seed(self, owner: DefaultStrategy, params: Params, optimizers: Optimizers, state: dict[str, Any],
             generator: torch.Generator) -> int:
        """Append up to n_seed seeds (fewer under the owner's cap_max; none when N = 0: no box)."""
        n_before = num_gaussians(params)
        n = min(self.n_seed, owner.room(n_before))
        if n <= 0 or n_before == 0:
            return 0
        rows = self.new_seed_rows(params, state, n, generator)
        if rows is None:
            return 0
        return add_seeds(params, optimizers, state["stats"], rows)


@dataclass
class SeedingStrategy(ExplorationStrategy):
    """Random Seeding on top of 3DGS adaptive density control."""

    seeding: RandomSeeding = field(default_factory=RandomSeeding)
    """Random Seeding (far side)."""
