"""Random Seeding and Random Splitting as gsplat strategies.

gsplat's simple_trainer and nerfstudio's splatfacto dispatch on the strategy's type
(``isinstance(strategy, DefaultStrategy)``), so the strategies here subclass
``gsplat.strategy.DefaultStrategy`` and keep its method signatures. Each ``step_post_backward``
first runs gsplat's own densification (``super()``: gradient statistics, clone, split, prune,
exactly as the installed gsplat does them) and then the exploration operators of
``exploregs_plugin.strategies``, with the paper's defaults:

- Random Splitting (:class:`SplitStrategy`): ``n_split`` = 20 Gaussians drawn without
  replacement in proportion to their mean scale (``draw_rows(split_weights(...))``) and split by
  ``ops.split`` (two children from the parent's Gaussian, scales / 1.6), every ``split_every`` = 1
  step with ``refine_start_iter < step < refine_stop_iter``.
- Random Seeding (:class:`SeedStrategy`): ``n_seed`` = 20 Gaussians uniform in the box of the
  current centres (``seed_rows``: scale and opacity grow with the distance from the scene
  centre) on every step where gsplat refines. While seeding is active gsplat's world-size prune
  uses ``seed_prune_scale3d`` (10 x scene scale) instead of ``prune_scale3d``, so far seeds
  survive: the field is swapped for the duration of ``super().step_post_backward`` (only gsplat's
  prune reads it there).
- :class:`SeedSplitStrategy`: both; on a step where both fire the split runs first.

Rows. The ops of ``exploregs_plugin.strategies.ops`` re-index every parameter together with its
Adam state (``exp_avg``, ``exp_avg_sq``) and are handed gsplat's state dict as their ``stats``:
they apply the same row change to every tensor in it (``grad2d``, ``count``, ``radii``) and leave
the rest (``scene_scale``, the generator) alone, as gsplat's own ops do. Children inherit their
parent's statistics and start with zero moments (as in gsplat's split); seeds start with zero
moments and zero statistics.

Randomness. gsplat passes no generator, so each strategy owns one, seeded with ``seed`` and made
on the parameters' device at its first use (the device is unknown before, which is also why
gsplat creates its own state tensors on the first step). gsplat's own split still draws from
torch's global generator.
"""

from __future__ import annotations

import contextlib
import dataclasses
import re
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from typing import Any, TypeVar

import torch
from torch import Tensor

try:
    import gsplat
    from gsplat.strategy import DefaultStrategy
except ImportError as exc:  # one line, whatever part of gsplat failed to import
    raise ImportError(
        f"exploregs_plugin.integrations.gsplat needs gsplat: pip install gsplat==1.5.3 ({exc})"
    ) from None

from ..strategies import ops
from ..strategies.base import StrategyError
from ..strategies.budget import PAPER_N_SEED, PAPER_N_SPLIT, PAPER_SPLIT_EVERY
from ..strategies.ops import Optimizers, Params, num_gaussians
from ..strategies.seeding import SeedingMixin, seed_rows
from ..strategies.splitting import draw_rows, split_weights

__all__ = [
    "ExplorationStrategy",
    "RADII_PAIRS",
    "SEED_PARAM_KEYS",
    "SeedSplitStrategy",
    "SeedStrategy",
    "SplitStrategy",
    "radii_layout",
    "seed_params",
    "sh_rest_count",
]


def _version(text: str) -> tuple[int, ...]:
    return tuple(int(part) for part in re.findall(r"\d+", text)[:2])


RADII_PAIRS: bool = _version(gsplat.__version__) >= (1, 5)
"""Whether the installed gsplat renders and reads one radius per image axis (``[C, N, 2]``,
packed ``[nnz, 2]``, gsplat >= 1.5) rather than one radius (``[C, N]``, packed ``[nnz]``, gsplat
< 1.5, e.g. the 1.4.0 that nerfstudio 1.1.5 pins)."""

SEED_PARAM_KEYS: dict[str, tuple[str, ...]] = {
    "means": ("means",),
    "scales": ("scales",),
    "quats": ("quats",),
    "opacities": ("opacities",),
    "sh0": ("sh0", "features_dc"),
    "shN": ("shN", "features_rest"),
}
"""Each row that ``seed_rows`` makes -> the parameter names it fills: gsplat's simple_trainer
calls the SH coefficients ``sh0``/``shN``, nerfstudio's splatfacto ``features_dc``/``features_rest``."""


# ---------------------------------------------------------------------------- pure functions
def radii_layout(radii: Tensor, packed: bool, pairs: bool) -> Tensor:
    """``radii`` in the layout a gsplat version reads: pairs ([C, N, 2] / packed [nnz, 2]) when
    ``pairs``, else one radius ([C, N] / packed [nnz]).

    A renderer and a strategy of different gsplat versions would otherwise disagree (gsplat 1.5's
    strategy reads ``(radii > 0).all(-1)`` and fails on [C, N]). The conversions keep what both
    versions read: a Gaussian is visible when its radius pair is positive on both axes, and its
    screen size is the larger one; one radius becomes the pair (r, r), a pair becomes its larger
    value where both are positive, else 0.
    """
    dims = (1, 2) if packed else (2, 3)
    if radii.dim() not in dims or (radii.dim() == dims[1] and radii.shape[-1] != 2):
        layouts = "[nnz] or [nnz, 2]" if packed else "[C, N] or [C, N, 2]"
        raise StrategyError(f"info['radii'] has shape {tuple(radii.shape)}; expected {layouts} (packed={packed})")
    has_pairs = radii.dim() == dims[1]
    if has_pairs == pairs:
        return radii
    if pairs:
        return radii.unsqueeze(-1).expand(*radii.shape, 2)
    return torch.where((radii > 0).all(dim=-1), radii.max(dim=-1).values, torch.zeros_like(radii[..., 0]))


def _sources(params: Mapping[str, Tensor]) -> dict[str, str]:
    """Parameter name -> the ``seed_rows`` row that fills it; raises naming the names none fills."""
    source = {name: row for row, names in SEED_PARAM_KEYS.items() for name in names}
    unknown = sorted(name for name in params if name not in source)
    if unknown:
        raise StrategyError(
            f"Random Seeding cannot fill parameters {unknown} of new seeds; it fills {sorted(source)}"
        )
    return {name: source[name] for name in params}


def sh_rest_count(params: Mapping[str, Tensor]) -> int:
    """K - 1, the higher SH coefficients per colour channel (0 without ``shN``/``features_rest``)."""
    for name in SEED_PARAM_KEYS["shN"]:
        if name in params:
            return params[name].shape[1:].numel() // 3
    return 0


def seed_params(rows: Mapping[str, Tensor], params: Mapping[str, Tensor]) -> dict[str, Tensor]:
    """``seed_rows``' rows under the names and row shapes of ``params``.

    Each row is reshaped to its parameter's row shape: ``opacities`` [S] -> [S, 1] (nerfstudio),
    ``sh0`` [S, 1, 3] -> ``features_dc`` [S, 3] (nerfstudio) or kept [S, 1, 3] (gsplat), ``shN``
    [S, K-1, 3] -> ``shN``/``features_rest``. A parameter no seed row fills (e.g. simple_trainer's
    appearance ``features``/``colors``) raises one line naming it.
    """
    out = {}
    for name, row_name in _sources(params).items():
        row, shape = rows[row_name], params[name].shape[1:]
        if row.shape[1:].numel() != shape.numel():
            raise StrategyError(
                f"parameter '{name}' has rows of shape {tuple(shape)}, "
                f"a seed's '{row_name}' has {tuple(row.shape[1:])}"
            )
        out[name] = row.reshape(row.shape[0], *shape)
    return out


@contextlib.contextmanager
def _field_set_to(obj: Any, name: str, value: Any) -> Iterator[None]:
    """``obj.name = value`` inside the block, the old value restored after it (also on error)."""
    saved = getattr(obj, name)
    setattr(obj, name, value)
    try:
        yield
    finally:
        setattr(obj, name, saved)


# ---------------------------------------------------------------------------- strategies
ExplorationT = TypeVar("ExplorationT", bound="ExplorationStrategy")


@dataclass
class ExplorationStrategy(DefaultStrategy):
    """gsplat's DefaultStrategy plus a hook, :meth:`explore`, that runs after its densification
    on every step before refine_stop_iter; no operator of its own (the subclasses add them)."""

    seed: int = 0
    """Seed of the strategy's own torch.Generator (gsplat's trainers pass none)."""

    def __post_init__(self) -> None:
        """Field checks; subclasses extend (super() first)."""

    @classmethod
    def from_default(cls: type[ExplorationT], strategy: DefaultStrategy, **fields: Any) -> ExplorationT:
        """This class with every gsplat setting of ``strategy`` (e.g. the DefaultStrategy that
        splatfacto builds from its config) and ``fields`` on top."""
        if not isinstance(strategy, DefaultStrategy):
            raise StrategyError(
                f"{cls.__name__}.from_default needs a gsplat DefaultStrategy, got {type(strategy).__name__}"
            )
        base = {f.name: getattr(strategy, f.name) for f in dataclasses.fields(DefaultStrategy)}
        return cls(**{**base, **fields})

    # ------------------------------------------------------------------ hooks for subclasses
    def prune_scale3d_at(self, step: int) -> float:
        """World-size prune threshold (x scene scale) for gsplat's prune at ``step``."""
        return self.prune_scale3d

    def explore(
        self, params: Params, optimizers: Optimizers, state: dict[str, Any], step: int, generator: torch.Generator
    ) -> dict[str, int]:
        """Exploration operators, after gsplat's densification, on every step with
        ``step < refine_stop_iter``; returns counts. Subclasses extend (super() first)."""
        return {}

    def refines_at(self, step: int) -> bool:
        """Whether gsplat's DefaultStrategy grows and prunes at ``step`` (its own condition)."""
        return (
            self.refine_start_iter < step < self.refine_stop_iter
            and step % self.refine_every == 0
            and step % self.reset_every >= self.pause_refine_after_reset
        )

    # ------------------------------------------------------------------ gsplat's contract
    def initialize_state(self, scene_scale: float = 1.0) -> dict[str, Any]:
        """gsplat's state plus ``generator`` (None until the first step, then a torch.Generator
        on the parameters' device seeded with ``seed``)."""
        state = super().initialize_state(scene_scale)
        state["generator"] = None
        return state

    def step_post_backward(
        self,
        params: Params,
        optimizers: Optimizers,
        state: dict[str, Any],
        step: int,
        info: dict[str, Any],
        packed: bool = False,
    ) -> dict[str, int]:
        """gsplat's densification, then :meth:`explore`; returns the exploration counts (gsplat's
        trainers ignore them)."""
        if "radii" in info:
            radii = radii_layout(info["radii"], packed, RADII_PAIRS)
            if radii is not info["radii"]:
                info = {**info, "radii": radii}
        with _field_set_to(self, "prune_scale3d", self.prune_scale3d_at(step)):
            super().step_post_backward(params, optimizers, state, step, info, packed=packed)
        if step >= self.refine_stop_iter:
            return {}
        counts = self.explore(params, optimizers, state, step, self._generator(state, params["means"].device))
        if self.verbose and any(counts.values()):
            done = ", ".join(f"{key} {value}" for key, value in counts.items())
            print(f"Step {step}: {done}. Now having {num_gaussians(params)} GSs.")
        return counts

    def _generator(self, state: dict[str, Any], device: torch.device) -> torch.Generator:
        generator = state.get("generator")
        if generator is None:
            generator = state["generator"] = torch.Generator(device=device).manual_seed(self.seed)
        return generator


@dataclass
class SplitStrategy(ExplorationStrategy):
    """gsplat's DefaultStrategy + Random Splitting (near side)."""

    n_split: int = PAPER_N_SPLIT
    """Gaussians split per splitting step, drawn in proportion to mean scale (0 disables)."""
    split_every: int = PAPER_SPLIT_EVERY
    """Splitting interval in steps, inside refine_start_iter < step < refine_stop_iter."""

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.n_split < 0:
            raise StrategyError(f"n_split must be >= 0, got {self.n_split}")
        if self.split_every < 1:
            raise StrategyError(f"split_every must be >= 1, got {self.split_every}")

    def explore(
        self, params: Params, optimizers: Optimizers, state: dict[str, Any], step: int, generator: torch.Generator
    ) -> dict[str, int]:
        counts = super().explore(params, optimizers, state, step, generator)
        counts["random_split"] = 0
        if self.n_split and step > self.refine_start_iter and step % self.split_every == 0:
            counts["random_split"] = self.random_split(params, optimizers, state, generator)
        return counts

    def random_split(
        self, params: Params, optimizers: Optimizers, state: dict[str, Any], generator: torch.Generator
    ) -> int:
        """Split up to n_split Gaussians drawn by mean scale (all of them when N is smaller)."""
        n = num_gaussians(params)
        idx = draw_rows(split_weights(params["scales"]), min(self.n_split, n), generator)
        mask = torch.zeros(n, dtype=torch.bool, device=params["means"].device)
        mask[idx] = True
        return ops.split(params, optimizers, state, mask, generator)


@dataclass
class SeedStrategy(ExplorationStrategy):
    """gsplat's DefaultStrategy + Random Seeding (far side)."""

    n_seed: int = PAPER_N_SEED
    """Seeds added on every step where gsplat refines (0 disables)."""
    seed_prune_scale3d: float = SeedingMixin.seed_prune_scale3d
    """While seeding is active, gsplat's world-size prune uses this (x scene scale) instead of
    prune_scale3d, so far seeds survive."""
    seed_min_scale: float = SeedingMixin.seed_min_scale
    """Smallest seed scale, as a fraction of the scene scale (guards a seed on the centre)."""
    seed_center: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Scene centre of the seed rule (scale and opacity grow with the distance from it); both
    trainers centre their normalised scenes on the origin by default."""

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.n_seed < 0:
            raise StrategyError(f"n_seed must be >= 0, got {self.n_seed}")
        if not self.seed_prune_scale3d > 0.0:
            raise StrategyError(f"seed_prune_scale3d must be positive, got {self.seed_prune_scale3d}")

    def check_sanity(self, params: Params, optimizers: Optimizers) -> None:
        """gsplat's checks, and that every parameter can be filled for new seeds."""
        super().check_sanity(params, optimizers)
        _sources(params)

    def prune_scale3d_at(self, step: int) -> float:
        if self.n_seed and step < self.refine_stop_iter:
            return self.seed_prune_scale3d
        return super().prune_scale3d_at(step)

    def explore(
        self, params: Params, optimizers: Optimizers, state: dict[str, Any], step: int, generator: torch.Generator
    ) -> dict[str, int]:
        counts = super().explore(params, optimizers, state, step, generator)
        counts["seeded"] = 0
        if self.n_seed and self.refines_at(step):
            counts["seeded"] = self.add_seeds(params, optimizers, state, generator)
        return counts

    def add_seeds(
        self, params: Params, optimizers: Optimizers, state: dict[str, Any], generator: torch.Generator
    ) -> int:
        """Append n_seed seeds uniform in the box of the current centres (none when N = 0 or no
        centre is finite: there is no box)."""
        if num_gaussians(params) == 0:
            return 0
        scene_scale = float(state["scene_scale"])
        rows = seed_rows(
            params["means"],
            params["scales"],
            self.n_seed,
            generator,
            torch.tensor(self.seed_center),
            sh_rest_count(params),
            min_scale=self.seed_min_scale * scene_scale,
        )
        if rows is None:
            return 0
        return ops.append(params, optimizers, state, seed_params(rows, params))


@dataclass
class SeedSplitStrategy(SeedStrategy, SplitStrategy):
    """gsplat's DefaultStrategy + Random Splitting + Random Seeding (split first, then seeds)."""
