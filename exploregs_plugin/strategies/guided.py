"""Guided seeding: seeds on the rays of the training pixels whose recent error is highest.

Uniform Random Seeding puts most seeds in empty space, where probation prunes them again. Here
each training step leaves a coarse error map of its view (mean |render - target| over cells of
``guide_cell`` pixels, and the cells' target colours) in the strategy state; at a seeding step
the seeds go through cells drawn with probability proportional to error^``guide_power`` over
the stored maps, at a random point of the cell, at depths stratified over the batch between
``guide_near`` x extent and the far bound (the farthest corner of the Gaussians' box seen from
that camera, or ``guide_far`` x extent), and take the cell's target colour. A seed's scale is its
cell's footprint at its depth, z * cell / f. Seed flags, the relaxed size prune and probation
are Seeding's: seeds at the wrong depth fade and are pruned.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Literal

import torch
import torch.nn.functional as F
from torch import Tensor

from ..rasterizer.sh import rgb_to_sh0
from .errors import StrategyError
from .exploration import ExplorationStrategy
from .geometry import random_unit_quats
from .observation import ViewObservation
from .row_ops import Params
from .requirements import VIEW_ERRORS
from .seeding import RandomSeeding, seed_box

if TYPE_CHECKING:
    from .default import DefaultStrategy

DepthSampling = Literal["log", "inverse"]


MAX_CELLS_PER_SIDE = 128
"""Longest side of a stored error map in cells: bounds the state (and checkpoints) on large images."""


def view_cell(cell: int, width: int, height: int) -> int:
    """The cell size used for a ``width`` x ``height`` view: ``cell``, or larger so the map's longer
    side has at most MAX_CELLS_PER_SIDE cells (a 1080p view: 15 px cells, 128 x 72, 37k values)."""
    return max(cell, math.ceil(max(width, height) / MAX_CELLS_PER_SIDE))


def coarse_view(error: Tensor, target: Tensor, cell: int) -> tuple[Tensor, Tensor]:
    """error [H, W], target [H, W, 3] -> mean error [h, w] and mean colour [h, w, 3] over cells of
    ``cell`` x ``cell`` pixels (h = ceil(H / cell); partial edge cells average what they hold)."""
    e = F.avg_pool2d(error[None, None].float(), cell, ceil_mode=True)[0, 0]
    c = F.avg_pool2d(target.permute(2, 0, 1)[None].float(), cell, ceil_mode=True)[0].permute(1, 2, 0)
    return e, c


def stratified_depths(n: int, near: Tensor, far: Tensor, mode: DepthSampling, generator: torch.Generator) -> Tensor:
    """``n`` depths in [near, far] (per-sample bounds [n]), one per stratum of [0, 1) in random
    order, uniform in log depth ('log': each octave of distance gets the same share) or in
    inverse depth ('inverse': uniform in disparity)."""
    dev = near.device
    strata = torch.randperm(n, generator=generator, device=generator.device).to(dev, near.dtype)
    u = (strata + torch.rand(n, generator=generator, device=generator.device).to(dev, near.dtype)) / n
    if mode == "log":
        return near * torch.exp(u * torch.log(far / near))
    if mode == "inverse":
        return 1.0 / (1.0 / near + u * (1.0 / far - 1.0 / near))
    raise StrategyError(f"guide_depth must be 'log' or 'inverse', got {mode!r}")


def far_bounds(means: Tensor, viewmats: Tensor, minimum: Tensor,
               box: tuple[Tensor, Tensor] | None = None) -> Tensor:
    """Per camera [V]: the largest camera depth z of the 8 corners of ``box`` (default: the
    centres' box, so seeds can reach the farthest content), at least ``minimum`` [V].
    viewmats: [V, 4, 4]."""
    bounds = seed_box(means.detach()) if box is None else box
    if bounds is None:
        return minimum
    lo, hi = bounds
    corners = torch.stack([torch.where(torch.tensor([(k >> a) & 1 for a in range(3)], device=lo.device).bool(), hi, lo)
                           for k in range(8)])  # [8, 3]
    z = torch.einsum("vj,cj->vc", viewmats[:, 2, :3], corners) + viewmats[:, 2, 3:4]  # [V, 8]
    return torch.maximum(z.max(dim=1).values, minimum)


def guided_seed_rows(
    views: dict[int, dict[str, Tensor]],
    n: int,
    generator: torch.Generator,
    means: Tensor,
    sh_rest: int,
    *,
    power: float,
    near: float,
    far: float | None,
    depth: DepthSampling,
    opacity: float,
    scale_mult: float,
    box: tuple[Tensor, Tensor] | None = None,
) -> dict[str, Tensor] | None:
    """Raw rows of ``n`` guided seeds from the stored views (None when no view has error).

    views: view index -> {"error" [h, w], "colour" [h, w, 3], "viewmat" [4, 4], "K" [3, 3],
    "size" [2] (W, H), "cell" [] (the map's cell side in pixels)}; means: [N, 3] current centres
    (for the far bound); near, far: world units; ``box`` (lo [3], hi [3]) bounds the far depth
    instead of the centres' box when given.
    """
    if not views or n <= 0:
        return None
    keys = sorted(views)
    dtype, dev = means.dtype, means.device
    errors = [views[k]["error"].to(dev, dtype).flatten() for k in keys]
    weights = torch.cat(errors).clamp_min(0.0) ** power
    if not bool(torch.isfinite(weights).all()) or float(weights.sum()) <= 0.0:
        return None
    # with replacement: a bad cell may take several seeds, at different (stratified) depths
    picks = torch.multinomial(weights.to(generator.device), n, replacement=True, generator=generator).to(dev)
    offsets = torch.cumsum(torch.tensor([0] + [e.numel() for e in errors], device=dev), 0)
    which = torch.searchsorted(offsets[1:], picks, right=True)  # index into keys
    local = picks - offsets[which]
    widths = torch.tensor([views[k]["error"].shape[1] for k in keys], device=dev)
    cy, cx = local // widths[which], local % widths[which]
    viewmats = torch.stack([views[k]["viewmat"].to(dev, dtype) for k in keys])
    Ks = torch.stack([views[k]["K"].to(dev, dtype) for k in keys])
    sizes = torch.stack([views[k]["size"].to(dev, dtype) for k in keys])
    cells = torch.stack([views[k]["cell"].to(dev, dtype) for k in keys])[which]
    jitter = torch.rand(n, 2, generator=generator, device=generator.device, dtype=dtype).to(dev)
    px = torch.minimum((cx + jitter[:, 0]) * cells, sizes[which, 0])
    py = torch.minimum((cy + jitter[:, 1]) * cells, sizes[which, 1])
    near_t = torch.full((n,), near, dtype=dtype, device=dev)
    far_v = far_bounds(means, viewmats, torch.full((len(keys),), 2.0 * near, dtype=dtype, device=dev), box)
    far_t = far_v[which] if far is None else torch.full((n,), max(far, 2.0 * near), dtype=dtype, device=dev)
    z = stratified_depths(n, near_t, far_t, depth, generator)
    K = Ks[which]
    cam = torch.stack([(px - K[:, 0, 2]) / K[:, 0, 0], (py - K[:, 1, 2]) / K[:, 1, 1], torch.ones_like(px)], -1)
    cam = cam * z[:, None]
    R, t = viewmats[which, :3, :3], viewmats[which, :3, 3]
    positions = torch.einsum("nji,nj->ni", R, cam - t)  # R^T (x - t)
    colours = torch.stack([views[keys[int(w)]]["colour"].to(dev, dtype)[int(y), int(x)]
                           for w, y, x in zip(which.tolist(), cy.tolist(), cx.tolist())])
    scale = (z * cells / K[:, 0, 0] * scale_mult).clamp_min(1e-9)
    logit = math.log(opacity / (1.0 - opacity))
    return {
        "means": positions,
        "scales": torch.log(scale).unsqueeze(-1).expand(n, 3).clone(),
        "quats": random_unit_quats(n, generator, dtype).to(dev),
        "opacities": torch.full((n,), logit, dtype=dtype, device=dev),
        "sh0": rgb_to_sh0(colours.clamp(0.0, 1.0)),
        "shN": torch.zeros(n, sh_rest, 3, dtype=dtype, device=dev),
    }


@dataclass
class GuidedSeeding(RandomSeeding):
    """Guided seeding: Random Seeding's schedule, flags and probation, with seeds placed on the
    rays of the pixels whose recent error is highest."""

    guide_cell: int = 4
    """Side in pixels of the cells of the stored error maps (memory: four values per cell and view);
    larger on big images, so a map's longer side has at most 128 cells."""
    guide_power: float = 2.0
    """Cells are drawn with probability proportional to error^power (higher: more to the worst)."""
    guide_near: float = 0.05
    """Nearest seed depth, as a fraction of the scene extent."""
    guide_far: float | None = None
    """Farthest seed depth, as a fraction of the scene extent. None: per camera, the farthest
    corner of the seed box (box_mode; 'aabb': the box of the current centres, so far content is
    in reach)."""
    guide_depth: DepthSampling = "log"
    """Depth sampling between the bounds: 'log' (each octave of distance gets the same share of
    seeds, so far content gets its share) or 'inverse' (uniform in disparity, near-heavy)."""
    guide_opacity: float = 0.3
    """Opacity of a new guided seed."""
    guide_scale: float = 1.0
    """Seed scale as a multiple of its cell's footprint at its depth (z * cell / f)."""

    requires = frozenset({VIEW_ERRORS})

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.guide_cell < 1 or self.guide_power < 0 or not 0.0 < self.guide_opacity < 1.0:
            raise StrategyError("guide_cell must be >= 1, guide_power >= 0 and guide_opacity in (0, 1)")
        if self.guide_near <= 0 or (self.guide_far is not None and self.guide_far <= self.guide_near):
            raise StrategyError(f"need 0 < guide_near < guide_far, got {self.guide_near}, {self.guide_far}")
        if self.guide_depth not in ("log", "inverse") or self.guide_scale <= 0:
            raise StrategyError("guide_depth must be 'log' or 'inverse' and guide_scale > 0")

    def observe(self, owner: DefaultStrategy, params: Params, state: dict[str, Any],
                view: ViewObservation) -> dict[str, int]:
        counts = super().observe(owner, params, state, view)
        seen = view.error
        if seen is None:
            raise StrategyError(f"{type(self).__name__} needs the view's error map: the pipeline gives it to "
                                f"strategies whose requirements() include VIEW_ERRORS")
        width, height = seen.target.shape[1], seen.target.shape[0]
        cell = view_cell(self.guide_cell, width, height)
        error, colour = coarse_view(seen.error.detach(), seen.target.detach(), cell)
        state.setdefault("views", {})[int(seen.index)] = {
            "error": error, "colour": colour, "viewmat": seen.viewmat.detach().to(error.device),
            "K": seen.K.detach().to(error.device),
            "size": torch.tensor([float(width), float(height)], device=error.device),
            "cell": torch.tensor(float(cell), device=error.device),
        }
        return counts

    def new_seed_rows(self, params: Params, state: dict[str, Any], n: int, generator: torch.Generator
                      ) -> dict[str, Tensor] | None:
        extent = state["scene_scale"]
        # the far bound comes from the seed box (box_mode); the paper's 'aabb' is the centres' box
        box = None if self.box_mode == "aabb" else seed_box(params["means"].detach(), self.box_mode, self.box_quantile,
                                                            state["scene_center"], extent)
        return guided_seed_rows(
            state.get("views", {}), n, generator, params["means"].detach(), params["shN"].shape[1],
            power=self.guide_power, near=self.guide_near * extent,
            far=None if self.guide_far is None else self.guide_far * extent, depth=self.guide_depth,
            opacity=self.guide_opacity, scale_mult=self.guide_scale, box=box,
        )


@dataclass
class GuidedSeedingStrategy(ExplorationStrategy):
    """Guided seeding on top of 3DGS adaptive density control."""

    seeding: GuidedSeeding = field(default_factory=GuidedSeeding)
    """Seeds on the rays of the pixels with the highest recent error (far side)."""
