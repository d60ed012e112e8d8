"""Our exploration operators as gsplat strategies, for trainers built on gsplat's strategy API
(gsplat's ``examples/simple_trainer.py``, nerfstudio's splatfacto).

Both trainers choose what to call from the strategy's type (``isinstance(strategy,
DefaultStrategy)`` / ``MCMCStrategy``), so the adapters subclass gsplat's classes and keep their
method signatures; the exploration itself is not written here. Each adapter holds the very
operator configs that eg-train's strategy of the same name holds (``RandomSplitting``,
``RandomSeeding``, ``PositionNoise`` of ``exploregs_plugin.strategies``, as nested fields under the
same names) and calls their hooks, so a change to an operator changes both trainers:

- :class:`GsplatExplorationStrategy` and its subclasses: gsplat's ``DefaultStrategy`` (its own
  statistics, clone, split and prune, as the installed gsplat does them) with the operators at
  the points where our ``ExplorationStrategy`` calls them on top of our Default: ``observe`` on
  each view inside the window, before the set changes; ``size_prune_factor`` as gsplat's world-size
  prune threshold (swapped in for the length of gsplat's step); ``extra_prune`` in the same
  refinement as gsplat's prune (seed probation); ``explore`` after gsplat's densification, every step.
- :class:`GsplatMCMCRayStrategy`: gsplat's ``MCMCStrategy`` type whose step is our
  ``MCMCStrategy`` (relocation, 5% growth to ``cap_max``, the noise ``noise`` along the ray), built
  from gsplat's fields.

What the adapters supply that eg-train supplies otherwise:

- Observations: :func:`~.gsplat_info.observations` turns gsplat's ``info`` into our views (radii
  as pairs, the 2D-mean gradient, the camera centre from ``info``'s camera, which gsplat's own
  info lacks: see :data:`~.gsplat_info.CAMERA_KEYS`).
- Layout: the operators read our parameter names and row shapes; nerfstudio's (``features_dc``
  [N, 3], ``features_rest``, ``opacities`` [N, 1]) are handed to them renamed and reshaped, with their
  Adam state, for the length of the step (:func:`our_layout`).
- Budget: operator fields left at None (``n_seed``, ``every``, ...) come from the exploration
  budget ``budget`` (as in eg-train; 'paper': 20 seeds every ``refine_every`` steps, 20 random
  splits per image and step), resolved for gsplat's refine window.
- Randomness: gsplat's trainers pass no generator, so each strategy owns one, seeded with ``seed``
  and made on the parameters' device at the first step (``state["generator"]``). gsplat's own split
  still draws from torch's global generator.
- Statistics: the operators' per-Gaussian statistics (seed flags, ``seed_seen``) are tensors of
  gsplat's state dict, so gsplat's ops and ours keep them aligned with the rows as they do
  ``grad2d`` and ``count``.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import re
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar, TypeVar

import torch
from torch import Tensor

try:
    import gsplat
    import gsplat.strategy as gs
except ImportError as exc:  # one line, whatever part of gsplat failed to import
    raise ImportError(
        f"exploregs_plugin.integrations.into_gsplat needs gsplat: pip install gsplat==1.5.3 ({exc})"
    ) from None

from ..strategies import row_ops
from ..strategies.base import StepContext, StrategyError
from ..strategies.budget import BUDGET_PRESETS, BudgetName, ExplorationBudget, resolve_budget
from ..strategies.exploration import (add_counts, first_size_prune_factor, operator_fields, operators_extra_prune,
                                      operators_summary)
from ..strategies.mcmc import NO_CAP, MCMCStrategy
from ..strategies.operator_contract import Operator
from ..strategies.row_ops import Optimizers, Params, num_gaussians
from ..strategies.position_noise import PositionNoise
from ..strategies.seeding import RandomSeeding
from ..strategies.splitting import RandomSplitting
from .gsplat_info import observations, radii_layout
from .patching import attribute_set_to

__all__ = [
    "GSPLAT_NOISE_LR",
    "OUR_NAMES",
    "RADII_PAIRS",
    "SEEDED",
    "GsplatExplorationStrategy",
    "GsplatMCMCRayStrategy",
    "GsplatRayStrategy",
    "GsplatSeedSplitStrategy",
    "GsplatSeedStrategy",
    "GsplatSplitStrategy",
    "our_layout",
]


def _version(text: str) -> tuple[int, ...]:
    return tuple(int(part) for part in re.findall(r"\d+", text)[:2])


RADII_PAIRS: bool = _version(gsplat.__version__) >= (1, 5)
"""Whether the installed gsplat renders and reads one radius per image axis (``[C, N, 2]``,
packed ``[nnz, 2]``, gsplat >= 1.5) rather than one radius (``[C, N]``, packed ``[nnz]``, gsplat
< 1.5, e.g. the 1.4.0 that nerfstudio 1.1.5 pins)."""

OUR_NAMES: dict[str, str] = {"features_dc": "sh0", "features_rest": "shN"}
"""nerfstudio's parameter names -> ours (gsplat's simple_trainer uses ours)."""

GSPLAT_NOISE_LR: float = gs.MCMCStrategy.noise_lr
"""gsplat's default ``noise_lr``: the only value :class:`GsplatMCMCRayStrategy` accepts for it."""

SEEDED: tuple[str, ...] = ("means", "scales", "quats", "opacities", "sh0", "shN")
"""The parameters Random Seeding makes rows of (``seed_rows``), in our names."""


# ---------------------------------------------------------------------------- parameter layout
def _ours(name: str, shape: torch.Size) -> tuple[str, tuple[int, ...]]:
    """The name and row shape the operators read for the trainer's parameter ``name`` of row
    shape ``shape``: ours for nerfstudio's names (:data:`OUR_NAMES`); opacities [] (a logit per
    row), sh0 [1, 3], shN [K-1, 3]; any other parameter as it is."""
    ours = OUR_NAMES.get(name, name)
    row = {"opacities": (), "sh0": (1, 3), "shN": (shape.numel() // 3, 3)}.get(ours, tuple(shape))
    if torch.Size(row).numel() != shape.numel():
        raise StrategyError(
            f"parameter '{name}' has rows of shape {tuple(shape)}; ExploreGS reads {ours} rows of shape {row}")
    return ours, row


def _reshape_rows(params: dict[str, Tensor], optimizers: dict[str, Any], shapes: Mapping[str, tuple[int, ...]]) -> None:
    """Each parameter whose row shape is not ``shapes[name]`` reshaped to it, with its Adam state
    (through ``ops``, so the optimizer keeps pointing at the parameter it steps)."""
    for name, shape in shapes.items():
        if tuple(params[name].shape[1:]) != shape:
            row_ops.update_params_and_optimizers(lambda _, p, s=shape: p.reshape(p.shape[0], *s),
                                             lambda _, v, s=shape: v.reshape(v.shape[0], *s),
                                             params, optimizers, names=[name])


@contextlib.contextmanager
def our_layout(params: Params, optimizers: Optimizers) -> Iterator[tuple[dict[str, Tensor], dict[str, Any]]]:
    """The trainer's parameters and optimizers under our names and row shapes inside the block
    (nerfstudio: ``features_dc`` [N, 3] -> ``sh0`` [N, 1, 3], ``features_rest`` -> ``shN``,
    ``opacities`` [N, 1] -> [N]); after it (also on error) the trainer's names and shapes, with
    whatever rows the block added, removed or moved, written back into ``params``.

    gsplat's layout is ours: then nothing is reshaped, and the block only carries the new
    parameter objects the ops made back into the trainer's dict (a ``ParameterDict`` too).
    """
    layout = {name: _ours(name, p.shape[1:]) for name, p in params.items()}
    names = {name: ours for name, (ours, _) in layout.items()}
    view = {names[name]: params[name] for name in params}
    opt_view = {names.get(name, name): opt for name, opt in optimizers.items()}
    theirs = {names[name]: tuple(params[name].shape[1:]) for name in params}
    _reshape_rows(view, opt_view, dict(layout.values()))
    try:
        yield view, opt_view
    finally:
        _reshape_rows(view, opt_view, theirs)
        for name, ours in names.items():
            params[name] = view[ours]


def _check_seeded(params: Mapping[str, Tensor]) -> None:
    """One line naming the parameters Random Seeding cannot make rows of, or lacks."""
    ours = {OUR_NAMES.get(name, name) for name in params}
    unknown, missing = sorted(ours - set(SEEDED)), sorted(set(SEEDED) - ours)
    if unknown or missing:
        raise StrategyError(
            f"Random Seeding cannot fill parameters {unknown} of new seeds; it fills {list(SEEDED)} "
            f"(nerfstudio's features_dc / features_rest for sh0 / shN), missing {missing}"
        )


# ---------------------------------------------------------------------------- shared helpers
def _state_generator(state: dict[str, Any], device: torch.device, seed: int) -> torch.Generator:
    """The strategy's own generator, kept in ``state["generator"]``; made on ``device`` with
    ``seed`` at its first use (gsplat's trainers pass none; the device is known only then)."""
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


PRINTED_COUNTS = "printed_counts"
"""Key of gsplat's state that sums the operators' counts between two progress lines: a dict, not
a tensor, so gsplat's ops (which re-index every tensor of the state) leave it alone."""


def _print_counts(verbose: bool, step: int, every: int, counts: Mapping[str, Any], params: Params,
                  state: dict[str, Any]) -> None:
    """gsplat-style progress line, once every ``every`` steps (gsplat's refinement steps) with the
    counts summed since the last line: the paper budget splits at every step, and a line per step
    would drown gsplat's own (the noise moves every step, so ``perturbed`` alone prints nothing).
    The sums stay tensors on the device until a line is printed."""
    if not verbose:  # a count may be a tensor on the device: read only to print it
        return
    summed = state.setdefault(PRINTED_COUNTS, {})
    for key, value in counts.items():
        if key != "perturbed":
            summed[key] = summed.get(key, 0) + value
    if step % max(1, every):
        return
    changed = {key: int(value) for key, value in summed.items() if int(value)}
    summed.clear()
    if changed:
        done = ", ".join(f"{key} {value}" for key, value in changed.items())
        print(f"Step {step}: {done} (since the last line). Now having {num_gaussians(params)} GSs.")


@functools.lru_cache(maxsize=16)
def _budget(name: str, start: int, stop: int, every: int, views: int) -> ExplorationBudget:
    # the scaled presets search their spread over the window's steps: once per window, not per step
    return resolve_budget(name, start, stop, every, views)


def _needs_camera(operators: list[tuple[str, Operator]]) -> bool:
    """Whether an operator reads the views' camera centres: ray noise, the one that does."""
    return any(isinstance(op, PositionNoise) and op.mode == "ray" for _, op in operators)


def _refuse_requirements(owner: Any, operators: list[tuple[str, Operator]]) -> None:
    """gsplat's info has the gradient and radii only: no error maps, no compositing weights."""
    needs = sorted({need for _, op in operators for need in type(op).requires})
    if needs:
        raise StrategyError(f"{type(owner).__name__}: gsplat's info cannot give what its operators require: {needs}")


# ---------------------------------------------------------------------------- DefaultStrategy + operators
ExplorationT = TypeVar("ExplorationT", bound="GsplatExplorationStrategy")


@dataclass
class GsplatExplorationStrategy(gs.DefaultStrategy):
    """gsplat's DefaultStrategy followed by our exploration operators, the dataclass fields of a
    subclass whose values are :class:`~exploregs_plugin.strategies.operator_contract.Operator` configs,
    run in the order of those fields (none here)."""

    budget: BudgetName = "paper"
    """Exploration budget for the operators' fields left at None: 'paper' (20 seeds every
    refine_every steps, 20 random splits per image and step) or a CPU preset (cpu-tiny, cpu-small,
    cpu-medium), as eg-train's --strategy.budget."""
    seed: int = 0
    """Seed of the strategy's own torch.Generator (gsplat's trainers pass none)."""
    scene_center: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Scene centre the operators read (Random Seeding: scale and opacity grow with the distance
    from it); both trainers centre their normalised scenes on the origin by default."""

    split_scale_factor: ClassVar[float] = 1.6
    """What a random split divides the scales by: gsplat's split's 1.6."""
    _step: ClassVar[tuple[list[tuple[str, Operator]], dict[str, Any], dict[str, Any]] | None] = None
    """(operators, their state, the step's counts) while :meth:`step_post_backward` runs gsplat's
    step, for :meth:`_prune_gs`; None otherwise."""

    def __post_init__(self) -> None:
        if self.budget not in BUDGET_PRESETS:
            raise StrategyError(f"unknown exploration budget '{self.budget}'; known presets: {sorted(BUDGET_PRESETS)}")
        _refuse_requirements(self, self.operators())

    @classmethod
    def from_default(cls: type[ExplorationT], strategy: gs.DefaultStrategy, **fields: Any) -> ExplorationT:
        """This class with every gsplat setting of ``strategy`` (e.g. the DefaultStrategy that
        splatfacto builds from its config) and ``fields`` on top."""
        if not isinstance(strategy, gs.DefaultStrategy):
            raise StrategyError(
                f"{cls.__name__}.from_default needs a gsplat DefaultStrategy, got {type(strategy).__name__}"
            )
        base = {f.name: getattr(strategy, f.name) for f in dataclasses.fields(gs.DefaultStrategy)}
        return cls(**{**base, **fields})

    # ------------------------------------------------------------------ what operators read of their owner
    def room(self, n_current: int) -> int:
        """gsplat's DefaultStrategy has no cap on the number of Gaussians."""
        return NO_CAP

    def operators(self) -> list[tuple[str, Operator]]:
        """(field name, operator) for every operator field, in the order they run."""
        return operator_fields(self)

    def resolved_operators(self, views_per_step: int = 1) -> list[tuple[str, Operator]]:
        """The operators with their fields left at None filled from :attr:`budget`, for gsplat's
        current refine window (simple_trainer rescales it after construction) and
        ``views_per_step`` images per step."""
        budget = _budget(self.budget, self.refine_start_iter, self.refine_stop_iter, self.refine_every,
                         max(1, views_per_step))
        return [(name, op.setup(budget)) for name, op in self.operators()]

    def operator_state(self, state: dict[str, Any]) -> dict[str, Any]:
        """The state our operators read: gsplat's state dict as their ``stats`` (gsplat's ops
        re-index its every tensor, as ours do), its scene scale, :attr:`scene_center`."""
        return {"stats": state, "scene_scale": float(state["scene_scale"]),
                "scene_center": torch.tensor(self.scene_center, dtype=torch.float32)}

    # ------------------------------------------------------------------ gsplat's contract
    def initialize_state(self, scene_scale: float = 1.0) -> dict[str, Any]:
        """gsplat's state plus ``generator`` (None until the first step)."""
        state = super().initialize_state(scene_scale)
        state["generator"] = None
        return state

    def check_sanity(self, params: Params, optimizers: Optimizers) -> None:
        """gsplat's checks; that every parameter can be read in our layout, and filled for new
        seeds when an operator seeds."""
        super().check_sanity(params, optimizers)
        for name, p in params.items():
            _ours(name, p.shape[1:])
        self._check_seeded(params)

    def _check_seeded(self, params: Params) -> None:
        # before the first seeds, not in the middle of a step with the set half changed
        if any(isinstance(op, RandomSeeding) for _, op in self.operators()):
            _check_seeded(params)

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
        """The operators' ``observe`` (inside the window), gsplat's densification with their
        world-size threshold and extra prune, then their ``explore``; returns the operators'
        counts (gsplat's trainers ignore them). ``lr``: the means learning rate, read only by the
        noise; None (simple_trainer and splatfacto pass none to a DefaultStrategy) reads it from
        ``optimizers["means"]``."""
        self._check_seeded(params)
        generator = _state_generator(state, params["means"].device, self.seed)
        # a gsplat without 2DGS (before key_for_gradient) reads means2d
        gradient = getattr(self, "key_for_gradient", "means2d")
        views = observations(info, num_gaussians(params), packed, gradient, _needs_camera(self.operators()))
        operators = self.resolved_operators(len(views))
        op_state = self.operator_state(state)
        counts: dict[str, Any] = {key: 0 for _, op in operators for key in op.COUNTS}
        if "radii" in info:  # gsplat's own code reads the installed version's layout
            radii = radii_layout(info["radii"], packed, RADII_PAIRS)
            if radii is not info["radii"]:
                info = {**info, "radii": radii}
        with our_layout(params, optimizers) as (p, o):
            if step < self.refine_stop_iter:
                for view in views:
                    for _, op in operators:
                        add_counts(counts, op.observe(self, p, op_state, view))
            with attribute_set_to(self, "prune_scale3d", self.size_prune_factor(operators, step)), \
                    attribute_set_to(self, "_step", (operators, op_state, counts)):
                super().step_post_backward(p, o, state, step, info, packed=packed)
            ctx = StepContext(p, o, op_state, step, views, _means_lr(o, lr), generator)
            for _, op in operators:
                add_counts(counts, op.explore(self, ctx))
        _print_counts(self.verbose, step, self.refine_every, counts, params, state)
        return counts

    def size_prune_factor(self, operators: list[tuple[str, Operator]], step: int) -> float:
        """gsplat's world-size prune threshold (x scene scale) at ``step``: the first operator's
        with an opinion (Random Seeding relaxes it while it seeds), else ``prune_scale3d``."""
        factor = first_size_prune_factor(operators, self, step)
        return self.prune_scale3d if factor is None else factor

    @torch.no_grad()
    def _prune_gs(self, params: Params, optimizers: Optimizers, state: dict[str, Any], step: int) -> int:
        """gsplat's prune, then the operators' ``extra_prune`` (seed probation) in the same
        refinement, before anything else of gsplat's step (a reset) changes the opacities."""
        pruned = super()._prune_gs(params, optimizers, state, step)
        if self._step is None:
            return pruned
        operators, op_state, counts = self._step
        mask, _ = operators_extra_prune(operators, self, params, op_state, step, None, counts)
        return pruned + (row_ops.remove(params, optimizers, state, mask) if mask is not None else 0)

    def exploration_summary(self, state: dict[str, Any]) -> dict[str, int]:
        """The operators' current totals (Random Seeding: ``seeds_alive``, ``seeds_unseen``), as
        eg-train logs them at each evaluation."""
        return operators_summary(self.operators(), self.operator_state(state))


@dataclass
class GsplatSplitStrategy(GsplatExplorationStrategy):
    """gsplat's DefaultStrategy + Random Splitting (near side): eg-train's ``split``."""

    splitting: RandomSplitting = field(default_factory=RandomSplitting)
    """Random Splitting (near side)."""


@dataclass
class GsplatSeedStrategy(GsplatExplorationStrategy):
    """gsplat's DefaultStrategy + Random Seeding (far side): eg-train's ``seed``."""

    seeding: RandomSeeding = field(default_factory=RandomSeeding)
    """Random Seeding (far side)."""


@dataclass
class GsplatSeedSplitStrategy(GsplatExplorationStrategy):
    """gsplat's DefaultStrategy + Random Splitting, then Random Seeding: eg-train's ``seedsplit``."""

    splitting: RandomSplitting = field(default_factory=RandomSplitting)
    """Random Splitting (near side), run first."""
    seeding: RandomSeeding = field(default_factory=RandomSeeding)
    """Random Seeding (far side), run after the splits."""


@dataclass
class GsplatRayStrategy(GsplatExplorationStrategy):
    """gsplat's DefaultStrategy + position noise along the viewing ray after every step:
    eg-train's ``ray``. The trainer puts the camera into ``info`` (``CAMERA_KEYS``)."""

    noise: PositionNoise = field(default_factory=lambda: PositionNoise(mode="ray"))
    """The position noise, along the ray by default."""


# ---------------------------------------------------------------------------- MCMC with ray noise
@dataclass
class GsplatMCMCRayStrategy(gs.MCMCStrategy):
    """gsplat's MCMCStrategy type whose step is our 3DGS-MCMC (``MCMCStrategy`` of
    exploregs_plugin.strategies): every ``refine_every`` steps inside the refine window dead
    Gaussians (opacity <= ``min_opacity``) are relocated onto live ones and the set grows by 5% up
    to ``cap_max`` (gsplat's rules: ``row_ops.relocate``, ``row_ops.sample_add``, eq. 9 in float64, drawn from
    this strategy's generator, on any device); after every step the positions get ``noise``, along
    the ray from the training camera by default, instead of gsplat's isotropic noise."""

    noise: PositionNoise = field(default_factory=lambda: PositionNoise(mode="ray"))
    """The position noise (eg-train's ``--strategy.noise``); its ``lr`` (5e5) takes the place of
    gsplat's ``noise_lr``, which is not read and must stay at gsplat's default."""
    seed: int = 0
    """Seed of the strategy's own torch.Generator: relocation, growth and the noise."""

    def __post_init__(self) -> None:
        self.mcmc()

    def mcmc(self) -> MCMCStrategy:
        """Our MCMC with gsplat's fields (simple_trainer rescales the refine window after
        construction, so it is made at each step)."""
        if self.noise_lr != GSPLAT_NOISE_LR:  # a setting that would do nothing is refused
            raise StrategyError(f"{type(self).__name__}'s noise is its operator `noise`: set noise.lr "
                                f"(--strategy.noise.lr) instead of gsplat's noise_lr (got {self.noise_lr})")
        # reset_every: the contract's schedule field; MCMC never resets opacity
        return MCMCStrategy(cap_max=self.cap_max, min_opacity=self.min_opacity, noise=self.noise,
                            refine_start_iter=self.refine_start_iter, refine_stop_iter=self.refine_stop_iter,
                            refine_every=self.refine_every, reset_every=self.refine_every)

    def initialize_state(self, scene_scale: float = 1.0) -> dict[str, Any]:
        """Our MCMC's state (``binoms``: the float64 binomial table of eq. 9, ``stats``) and
        ``generator`` (None until the first step)."""
        state = self.mcmc().initialize_state(scene_scale)
        state["generator"] = None
        return state

    def check_sanity(self, params: Params, optimizers: Optimizers) -> None:
        """gsplat's checks, and that every parameter can be read in our layout."""
        super().check_sanity(params, optimizers)
        for name, p in params.items():
            _ours(name, p.shape[1:])

    def step_post_backward(
        self,
        params: Params,
        optimizers: Optimizers,
        state: dict[str, Any],
        step: int,
        info: dict[str, Any],
        lr: float,
    ) -> dict[str, int]:
        """Our MCMC's step on gsplat's arguments; returns its counts (``relocated``, ``added``,
        ``perturbed``). Packed or not is read from ``info`` (``gaussian_ids`` is None unpacked)."""
        mcmc = self.mcmc()
        generator = _state_generator(state, params["means"].device, self.seed)
        views = observations(info, num_gaussians(params), info.get("gaussian_ids") is not None,
                             need_camera=_needs_camera([("noise", self.noise)]))
        with our_layout(params, optimizers) as (p, o):
            counts = mcmc.step_post_backward(p, o, state, step, views, lr=float(lr), generator=generator)
        _print_counts(self.verbose, step, self.refine_every, counts, params, state)
        return counts

