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

Ray perturbation. :class:`RayStrategy` is gsplat's DefaultStrategy plus the 3DGS-MCMC position
noise projected onto the viewing ray after every step (our ``RayPerturbationStrategy``);
:class:`MCMCRayStrategy` is gsplat's MCMCStrategy (relocation of dead Gaussians, 5% growth to
``cap_max``) whose isotropic noise is replaced by the same ray noise. Both call our operator
(``position_noise`` in 'ray' mode, as ``PositionNoise.perturb`` does). gsplat's ``info`` holds
no camera, so the trainer puts one in: ``camera_center`` [3], ``camtoworlds`` [C, 4, 4] or
``viewmats`` [C, 4, 4] (see :func:`camera_center`; the first camera's rays are used, as in our
pipeline for a step of several views).
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import re
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from typing import Any, TypeVar

import torch
from torch import Tensor

try:
    import gsplat
    from gsplat.strategy import DefaultStrategy, MCMCStrategy
except ImportError as exc:  # one line, whatever part of gsplat failed to import
    raise ImportError(
        f"exploregs_plugin.integrations.gsplat needs gsplat: pip install gsplat==1.5.3 ({exc})"
    ) from None

from ..strategies import ops
from .patching import attribute_set_to
from ..strategies.base import StrategyError
from ..strategies.budget import PAPER_N_SEED, PAPER_N_SPLIT, PAPER_SPLIT_EVERY
from ..strategies.ops import Optimizers, Params, num_gaussians
from ..strategies.perturbation import PositionNoise, position_noise
from ..strategies.relocation import N_MAX, binomial_table
from ..strategies.seeding import RandomSeeding, seed_rows
from ..strategies.splitting import draw_rows, split_weights

__all__ = [
    "CAMERA_KEYS",
    "ExplorationStrategy",
    "MCMCRayStrategy",
    "RADII_PAIRS",
    "RayStrategy",
    "SEED_PARAM_KEYS",
    "SeedSplitStrategy",
    "SeedStrategy",
    "SplitStrategy",
    "camera_center",
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


CAMERA_KEYS: tuple[str, ...] = ("camera_center", "camtoworlds", "viewmats")
"""Keys of ``info`` the ray noise reads the camera from, in this order: ``camera_center`` [3]
(our renderer's info), ``camtoworlds`` [..., C, 4, 4] (simple_trainer's name for the training
cameras), ``viewmats`` [..., C, 4, 4] (world-to-camera, the argument of gsplat's rasterization).
gsplat's own info carries none of them."""


def camera_center(info: Mapping[str, Any]) -> Tensor:
    """The first camera's centre [3] in world coordinates, from the first of :data:`CAMERA_KEYS`
    that ``info`` holds.

    camera-to-world M = [R | c]: the centre is its translation column c (whatever the axis
    convention, OpenCV or nerfstudio's OpenGL). World-to-camera V = [R | t] maps c to the origin,
    R c + t = 0, so c = -R^T t (R is a rotation: R^-1 = R^T, no inverse to guard).
    """
    for key in CAMERA_KEYS:
        value = info.get(key)
        if value is None:
            continue
        if key == "camera_center":
            return value.reshape(-1, 3)[0]
        if value.dim() < 2 or value.shape[-2:] != (4, 4):
            raise StrategyError(f"info['{key}'] must be [..., C, 4, 4], got {tuple(value.shape)}")
        matrix = value.reshape(-1, 4, 4)[0]
        return matrix[:3, 3] if key == "camtoworlds" else -(matrix[:3, :3].transpose(0, 1) @ matrix[:3, 3])
    raise StrategyError(
        "ray noise needs the training camera in info: set info['camtoworlds'] = camtoworlds [C, 4, 4] "
        "(or info['viewmats'] [C, 4, 4], or info['camera_center'] [3]) after rendering; gsplat's info "
        "has no camera"
    )


@contextlib.contextmanager
def _flat_opacities(params: Params, optimizers: Optimizers) -> Iterator[None]:
    """Opacities (and their Adam moments) as [N] inside the block, restored to [N, 1] after it.

    Our ops and ``position_noise`` read opacities [N] (gsplat's layout); nerfstudio keeps [N, 1].
    The reshape goes through ``ops.update_params_and_optimizers``, so the optimizer keeps pointing
    at the parameter it steps.
    """
    shape = params["opacities"].shape[1:]
    if shape.numel() != 1 or len(shape) == 0:
        yield
        return
    ops.update_params_and_optimizers(lambda _, p: p.reshape(-1), lambda _, v: v.reshape(-1), params, optimizers,
                                     names=["opacities"])
    try:
        yield
    finally:
        ops.update_params_and_optimizers(lambda _, p: p.reshape(-1, *shape), lambda _, v: v.reshape(-1, *shape),
                                         params, optimizers, names=["opacities"])


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


def _state_generator(state: dict[str, Any], device: torch.device, seed: int) -> torch.Generator:
    """The strategy's own generator, kept in ``state["generator"]``; made on ``device`` with
    ``seed`` at its first use (gsplat's trainers pass none)."""
    generator = state.get("generator")
    if generator is None:
        generator = state["generator"] = torch.Generator(device=device).manual_seed(seed)
    return generator


def _means_lr(optimizers: Optimizers, lr: float | None) -> float:
    """``lr`` if given, else the means optimizer's current learning rate (0.0 without one: the
    ray noise then refuses to run and says to pass lr)."""
    if lr is not None:
        return float(lr)
    optimizer = optimizers.get("means")
    return float(optimizer.param_groups[0]["lr"]) if optimizer is not None else 0.0


def _print_counts(verbose: bool, step: int, counts: Mapping[str, int], params: Params) -> None:
    """gsplat-style progress line for steps that changed the set (the noise moves every step,
    so ``perturbed`` alone prints nothing)."""
    changed = {key: value for key, value in counts.items() if key != "perturbed" and value}
    if verbose and changed:
        done = ", ".join(f"{key} {value}" for key, value in changed.items())
        print(f"Step {step}: {done}. Now having {num_gaussians(params)} GSs.")


@dataclass
class ExploreStep:
    """What one ``step_post_backward`` hands to the exploration operators (gsplat's ``info``
    as the trainer gave it)."""

    params: Params
    optimizers: Optimizers
    state: dict[str, Any]
    step: int
    info: Mapping[str, Any]
    lr: float
    generator: torch.Generator


def perturb_along_ray(strategy: Any, ctx: ExploreStep) -> int:
    """Our ray perturbation on gsplat's parameters: ``position_noise`` in 'ray' mode,
    eta = noise_lr lr sigmoid(-k (o - t)) Sigma z, projected onto the unit ray d from the camera
    centre to each Gaussian, (eta . d) d, added to the means in place (as
    ``PositionNoise.perturb`` does in our pipeline: the same draw from the generator and
    the same guard). Returns how many Gaussians it moved.

    ``strategy`` carries ``noise_lr``, ``noise_gate_k`` and ``noise_gate_t``. The camera comes
    from :func:`camera_center`; nerfstudio's opacities [N, 1] are read as [N].
    """
    params = ctx.params
    center = camera_center(ctx.info)
    n = num_gaussians(params)
    if n == 0:
        return 0
    if not (math.isfinite(ctx.lr) and ctx.lr > 0.0):
        raise StrategyError(
            f"{type(strategy).__name__} scales its noise by the means learning rate: pass lr=<current means lr> (> 0) "
            f"or keep an optimizer for 'means', got lr {ctx.lr}"
        )
    eta = position_noise(
        params["means"],
        params["quats"],
        params["scales"],
        params["opacities"].reshape(-1),
        strategy.noise_lr * ctx.lr,
        ctx.generator,
        mode="ray",
        camera_center=center,
        gate_k=strategy.noise_gate_k,
        gate_t=strategy.noise_gate_t,
    )
    # A non-finite row (degenerate parameters) must not spread NaN into the means.
    eta = torch.where(torch.isfinite(eta), eta, torch.zeros_like(eta))
    with torch.no_grad():
        params["means"].add_(eta.to(params["means"].dtype))
    return n


# ---------------------------------------------------------------------------- strategies
ExplorationT = TypeVar("ExplorationT", bound="ExplorationStrategy")


@dataclass
class ExplorationStrategy(DefaultStrategy):
    """gsplat's DefaultStrategy plus a hook, :meth:`explore`, that runs after its densification
    on every step where :meth:`explores_at` says so (before refine_stop_iter unless a subclass
    extends it); no operator of its own (the subclasses add them)."""

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

    def explores_at(self, step: int) -> bool:
        """Whether :meth:`explore` runs at ``step``: inside the refine window (subclasses extend)."""
        return step < self.refine_stop_iter

    def explore(self, ctx: ExploreStep) -> dict[str, int]:
        """Exploration operators, after gsplat's densification, on every step where
        :meth:`explores_at`; returns counts. Subclasses extend (super() first)."""
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
        lr: float | None = None,
    ) -> dict[str, int]:
        """gsplat's densification, then :meth:`explore`; returns the exploration counts (gsplat's
        trainers ignore them). ``lr``: the means learning rate, read only by the ray noise; None
        (simple_trainer and splatfacto pass none to a DefaultStrategy) reads it from
        ``optimizers["means"]``, which is what both give an MCMCStrategy."""
        if "radii" in info:
            radii = radii_layout(info["radii"], packed, RADII_PAIRS)
            if radii is not info["radii"]:
                info = {**info, "radii": radii}
        with attribute_set_to(self, "prune_scale3d", self.prune_scale3d_at(step)):
            super().step_post_backward(params, optimizers, state, step, info, packed=packed)
        if not self.explores_at(step):
            return {}
        generator = _state_generator(state, params["means"].device, self.seed)
        ctx = ExploreStep(params, optimizers, state, step, info, _means_lr(optimizers, lr), generator)
        counts = self.explore(ctx)
        _print_counts(self.verbose, step, counts, params)
        return counts


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

    def explore(self, ctx: ExploreStep) -> dict[str, int]:
        counts = super().explore(ctx)
        counts["random_split"] = 0
        step = ctx.step
        if self.n_split and self.refine_start_iter < step < self.refine_stop_iter and step % self.split_every == 0:
            counts["random_split"] = self.random_split(ctx.params, ctx.optimizers, ctx.state, ctx.generator)
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
    seed_prune_scale3d: float = RandomSeeding.prune_scale3d
    """While seeding is active, gsplat's world-size prune uses this (x scene scale) instead of
    prune_scale3d, so far seeds survive."""
    seed_min_scale: float = RandomSeeding.min_scale
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

    def explore(self, ctx: ExploreStep) -> dict[str, int]:
        counts = super().explore(ctx)
        counts["seeded"] = 0
        if self.n_seed and self.refines_at(ctx.step):
            counts["seeded"] = self.add_seeds(ctx.params, ctx.optimizers, ctx.state, ctx.generator)
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


@dataclass
class RayStrategy(ExplorationStrategy):
    """gsplat's DefaultStrategy + ray perturbation (our ``RayPerturbationStrategy``): after every
    step, 3DGS-MCMC's opacity-gated, covariance-shaped position noise projected onto the ray from
    the training camera, so only depth is explored. The trainer puts the camera into ``info``
    (:data:`CAMERA_KEYS`)."""

    noise_lr: float = PositionNoise.lr
    """Noise scale relative to the means learning rate (3DGS-MCMC: 5e5)."""
    noise_gate_k: float = PositionNoise.gate_k
    """Steepness k of the opacity gate sigmoid(-k (o - t))."""
    noise_gate_t: float = PositionNoise.gate_t
    """Opacity t at which the gate is one half."""

    def __post_init__(self) -> None:
        super().__post_init__()
        _check_noise_fields(self)

    def explores_at(self, step: int) -> bool:
        return True  # the noise runs on every step of the run, as in our pipeline

    def explore(self, ctx: ExploreStep) -> dict[str, int]:
        counts = super().explore(ctx)
        counts["perturbed"] = perturb_along_ray(self, ctx)
        return counts


def _check_noise_fields(strategy: Any) -> None:
    if not (math.isfinite(strategy.noise_lr) and strategy.noise_lr >= 0.0):
        raise StrategyError(f"noise_lr must be finite and >= 0, got {strategy.noise_lr}")
    if not (math.isfinite(strategy.noise_gate_k) and 0.0 <= strategy.noise_gate_t <= 1.0):
        raise StrategyError(
            f"noise_gate_k must be finite and noise_gate_t in [0, 1], got {strategy.noise_gate_k}, {strategy.noise_gate_t}"
        )


@dataclass
class MCMCRayStrategy(MCMCStrategy):
    """gsplat's MCMCStrategy with ray noise: every ``refine_every`` steps inside the refine window
    dead Gaussians (opacity <= ``min_opacity``) are relocated onto live ones and the set grows by
    5% up to ``cap_max``, as gsplat does; after every step the positions get our noise along the
    ray from the training camera instead of gsplat's isotropic noise.

    Relocation and growth: on CUDA gsplat's own (``compute_relocation`` is a CUDA kernel, and
    gsplat's ops draw from torch's global generator); on any other device our ops
    (``ops.relocate``, ``ops.sample_add``: the same eq. 9 update, in float64, drawn from this
    strategy's generator), so the strategy also runs on a CPU.
    """

    noise_gate_k: float = PositionNoise.gate_k
    """Steepness k of the opacity gate sigmoid(-k (o - t)) (gsplat's MCMC: 100)."""
    noise_gate_t: float = PositionNoise.gate_t
    """Opacity t at which the gate is one half (gsplat's MCMC: 0.005)."""
    seed: int = 0
    """Seed of the strategy's own torch.Generator: the noise everywhere, relocation and growth
    off CUDA."""

    def __post_init__(self) -> None:
        _check_noise_fields(self)
        if self.cap_max < 0:
            raise StrategyError(f"cap_max must be >= 0, got {self.cap_max}")

    def initialize_state(self) -> dict[str, Any]:
        """gsplat's state (``binoms``, float32 for its kernel), our float64 table for the ops off
        CUDA (C(50, 25) ~ 1e14 is not exact in float32) and ``generator`` (None until the first
        step)."""
        state = super().initialize_state()
        state["binoms_float64"] = binomial_table(N_MAX)
        state["generator"] = None
        return state

    def step_post_backward(
        self,
        params: Params,
        optimizers: Optimizers,
        state: dict[str, Any],
        step: int,
        info: dict[str, Any],
        lr: float,
    ) -> dict[str, int]:
        """gsplat's relocation and growth on its steps, then the ray noise; returns the counts."""
        device = params["means"].device
        state["binoms"] = state["binoms"].to(device)
        generator = _state_generator(state, device, self.seed)
        counts = {"relocated": 0, "added": 0}
        if self.refine_start_iter < step < self.refine_stop_iter and step % self.refine_every == 0:
            if device.type == "cuda":
                counts["relocated"] = self._relocate_gs(params, optimizers, state["binoms"])
                counts["added"] = self._add_new_gs(params, optimizers, state["binoms"])
                torch.cuda.empty_cache()
            else:
                binoms = state["binoms_float64"]
                with _flat_opacities(params, optimizers):
                    counts["relocated"] = self.relocate_dead(params, optimizers, binoms, generator)
                    counts["added"] = self.grow(params, optimizers, binoms, generator)
        ctx = ExploreStep(params, optimizers, state, step, info, float(lr), generator)
        counts["perturbed"] = perturb_along_ray(self, ctx)
        _print_counts(self.verbose, step, counts, params)
        return counts

    def relocate_dead(self, params: Params, optimizers: Optimizers, binoms: Tensor, generator: torch.Generator) -> int:
        """gsplat's rule (opacity <= min_opacity is dead) with our ``ops.relocate``."""
        dead = torch.sigmoid(params["opacities"].detach()) <= self.min_opacity
        return ops.relocate(params, optimizers, {}, dead, generator, binoms, self.min_opacity)

    def grow(self, params: Params, optimizers: Optimizers, binoms: Tensor, generator: torch.Generator) -> int:
        """gsplat's rule (N -> min(cap_max, floor(1.05 N))) with our ``ops.sample_add``."""
        n = num_gaussians(params)
        return ops.sample_add(params, optimizers, {}, max(0, min(self.cap_max, int(1.05 * n)) - n), generator,
                              binoms, self.min_opacity)
