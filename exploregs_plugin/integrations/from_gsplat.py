"""gsplat's own strategies inside eg-train: ``--strategy gsplat-default`` and ``--strategy gsplat-mcmc``.

:class:`GsplatDefaultStrategy` and :class:`GsplatMCMCStrategy` are our strategies (dataclass
configs of the ``Strategy`` contract, registered under the ``exploregs.strategies`` entry points)
whose ``step_post_backward`` runs gsplat 1.5.3's ``DefaultStrategy`` / ``MCMCStrategy`` itself on
our parameters, optimizers and run state. They make gsplat's code a reference for ours on the same
scene, seed and schedule.

- Fields: gsplat's fields with gsplat's defaults, as ``--strategy.*``. The four schedule fields
  (``refine_start_iter``, ``refine_stop_iter``, ``refine_every``, ``reset_every``) default to None
  and come from the run's schedule, which maps gsplat's 30k-step numbers (500, 15k, 100, 3k) to the
  same fractions of any run (docs/training.md); MCMC refines until 25/30 of the run (gsplat: 25k of
  30k). ``absgrad`` asks our renderers for the absolute gradient sums (``ABSOLUTE_GRADIENT``), which
  :func:`~.gsplat_info.gsplat_info` hands to gsplat. Not exposed: ``key_for_gradient`` (2DGS).
- Observations: :func:`~.gsplat_info.gsplat_info` turns the step's views into the ``info`` dict gsplat reads.
- Randomness: gsplat draws from torch's global generator (its split's children, MCMC's sampling
  and noise). Its step runs under ``torch.random.fork_rng`` with the global generator set to the
  run's generator's state, and the run's generator continues from where gsplat left it
  (:func:`global_rng_is`): gsplat's split draws the same children as our Default's split would, a
  run is determined by its seed and resumes exactly, and the global generator is left as it was.
- Counts: the same keys as our Default (``cloned``, ``split``, ``pruned``, ``opacity_reset``) and
  our MCMC (``relocated``, ``added``, ``perturbed``), read from gsplat's own return values.
- MCMC on CPU tensors uses torch stand-ins for gsplat's two CUDA-only helpers (relocation and
  covariance), see :mod:`exploregs_plugin.integrations.from_gsplat_cpu`; on CUDA gsplat's kernels run.

gsplat is imported when a strategy is first used (``check_sanity``), not when this module is
imported: the registry loads every entry point, and eg-train must work without gsplat installed.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import importlib
import math
import re
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any, ClassVar

import torch
from torch import Tensor

from ..schedule import Schedule
from ..strategies.base import StepContext, Strategy, StrategyError
from ..strategies.mcmc import MCMC_STOP_FRACTION, MCMCStrategy
from ..strategies.observation import ViewObservation
from ..strategies.requirements import ABSOLUTE_GRADIENT
from ..strategies.row_ops import Optimizers, Params, num_gaussians
from .from_gsplat_cpu import cpu_stand_ins
from .gsplat_info import gsplat_info

GSPLAT_VERSION = (1, 5)
"""The gsplat minor version whose info layout (radii pairs [C, N, 2]) and strategy internals
(``_grow_gs``, ``_prune_gs``, ``_relocate_gs``, ``_add_new_gs``) these adapters read."""

INSTALL = "pip install gsplat==1.5.3"


# ---------------------------------------------------------------------------- gsplat access
def _version(text: str) -> tuple[int, ...]:
    return tuple(int(part) for part in re.findall(r"\d+", text)[:2])


def gsplat_strategies() -> Any:
    """``gsplat.strategy`` (DefaultStrategy, MCMCStrategy); one line naming the install when
    gsplat is missing or of another minor version."""
    try:
        gsplat = importlib.import_module("gsplat")
        module = importlib.import_module("gsplat.strategy")
    except ImportError as exc:
        raise StrategyError(f"gsplat's strategies need gsplat: {INSTALL} ({exc})") from None
    if _version(gsplat.__version__) != GSPLAT_VERSION:
        raise StrategyError(
            f"gsplat's strategies are adapted to gsplat {'.'.join(map(str, GSPLAT_VERSION))}.x; "
            f"gsplat {gsplat.__version__} is installed ({INSTALL})"
        )
    return module


@functools.lru_cache(maxsize=None)
def _counting_classes() -> tuple[type, type]:
    """Subclasses of gsplat's two strategies that keep what each step did in ``self.counts``
    (gsplat returns the numbers from its private steps and only prints them)."""
    gs = gsplat_strategies()

    @dataclass
    class CountingDefault(gs.DefaultStrategy):
        def _grow_gs(self, params, optimizers, state, step):  # noqa: ANN001 - gsplat's signature
            n_dupli, n_split = super()._grow_gs(params, optimizers, state, step)
            self.counts.update(cloned=int(n_dupli), split=int(n_split))
            return n_dupli, n_split

        def _prune_gs(self, params, optimizers, state, step):  # noqa: ANN001
            if step > self.reset_every:  # gsplat's world-size prune, on after its first reset: said
                # apart, as our Default says it, for the collapse watch (collapse.deliberate_setback)
                too_big = params["scales"].detach().exp().max(dim=-1).values > self.prune_scale3d * state["scene_scale"]
                self.counts["pruned_too_big"] = int(too_big.sum())
            n_prune = super()._prune_gs(params, optimizers, state, step)
            self.counts["pruned"] = int(n_prune)
            # after the refine block only an opacity reset replaces params["opacities"]
            self.opacities_after_refine = params["opacities"]
            return n_prune

    @dataclass
    class CountingMCMC(gs.MCMCStrategy):
        def _relocate_gs(self, params, optimizers, binoms):  # noqa: ANN001
            n = super()._relocate_gs(params, optimizers, binoms)
            self.counts["relocated"] = int(n)
            return n

        def _add_new_gs(self, params, optimizers, binoms):  # noqa: ANN001
            n = super()._add_new_gs(params, optimizers, binoms)
            self.counts["added"] = int(n)
            return n

    return CountingDefault, CountingMCMC


@contextlib.contextmanager
def global_rng_is(generator: torch.Generator) -> Iterator[None]:
    """Inside the block torch's global generator of ``generator``'s device continues the run's
    generator: it starts from its state, and the run's generator takes the state gsplat leaves.
    gsplat's draws (``torch.randn`` etc. without a generator) are then the very numbers our own
    strategies would draw from the run's generator at that point; the global generator is restored
    after the block."""
    device = generator.device
    cuda = device.type == "cuda"
    with torch.random.fork_rng(devices=[device] if cuda else []):
        if cuda:
            torch.cuda.set_rng_state(generator.get_state(), device)
        else:
            torch.set_rng_state(generator.get_state())
        yield
        generator.set_state(torch.cuda.get_rng_state(device) if cuda else torch.get_rng_state())


# ---------------------------------------------------------------------------- strategies
@dataclass
class GsplatStrategy(Strategy):
    """Shared part: gsplat's state kept under ``state["gsplat"]`` (gsplat's ops re-index every
    tensor of the dict they are given, so our ``scene_center`` must not be in it)."""

    verbose: bool = False
    """gsplat prints what each refinement did."""

    GSPLAT_CLASS: ClassVar[str] = ""
    """The name of the gsplat strategy class (in ``gsplat.strategy``) the adapter runs."""

    def check_sanity(self, params: Params, optimizers: Optimizers) -> None:
        """Our checks, and that gsplat is importable (one line with the install otherwise)."""
        super().check_sanity(params, optimizers)
        gsplat_strategies()

    def gsplat_fields(self) -> dict[str, Any]:
        """Our values of the fields gsplat's class has (the other, ``key_for_gradient``, keeps
        gsplat's default; ``reset_every`` is ours only for MCMC)."""
        theirs = {f.name for f in dataclasses.fields(getattr(gsplat_strategies(), self.GSPLAT_CLASS))}
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name in theirs}


@dataclass
class GsplatDefaultStrategy(GsplatStrategy):
    """gsplat 1.5.3's DefaultStrategy (3DGS clone, split, prune) run inside eg-train."""

    GSPLAT_CLASS = "DefaultStrategy"

    prune_opa: float = 0.005
    """Prune Gaussians whose opacity is below this (gsplat's default)."""
    grow_grad2d: float = 0.0002
    """Clone/split Gaussians whose view-averaged NDC gradient norm exceeds this."""
    absgrad: bool = False
    """gsplat's AbsGS statistic: the sums over the pixels of |dL/dx| and |dL/dy| of each pixel
    instead of the summed gradient (gsplat pairs it with grow_grad2d 0.0008)."""
    grow_scale3d: float = 0.01
    """Clone when the largest scale is at most this x scene scale, else split."""
    grow_scale2d: float = 0.05
    """Also split when the screen size (max radius / max(W, H)) exceeds this, before
    refine_scale2d_stop_iter."""
    prune_scale3d: float = 0.1
    """After step reset_every, prune Gaussians larger than this x scene scale."""
    prune_scale2d: float = 0.15
    """Also prune when the screen size exceeds this, before refine_scale2d_stop_iter."""
    refine_scale2d_stop_iter: int = 0
    """The screen-size rules apply before this step (0: never, gsplat's default)."""
    pause_refine_after_reset: int = 0
    """No refinement in the first this-many steps of each reset_every period."""
    revised_opacity: bool = False
    """Split children get opacity 1 - sqrt(1 - o) (arXiv:2404.06109) instead of o."""

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.cap_max is not None:
            raise StrategyError("gsplat's DefaultStrategy has no cap on the number of Gaussians: leave cap_max unset")

    def requirements(self) -> frozenset[str]:
        required = super().requirements()
        return required | {ABSOLUTE_GRADIENT} if self.absgrad else required

    def gsplat_strategy(self) -> Any:
        strategy = _counting_classes()[0](**self.gsplat_fields())
        strategy.counts = {}
        strategy.opacities_after_refine = None
        return strategy

    def initialize_state(self, scene_scale: float = 1.0, scene_center: Tensor | None = None) -> dict[str, Any]:
        """Our state plus gsplat's under ``gsplat`` (``grad2d``, ``count``: None until the first
        step; ``scene_scale``; ``radii`` when the screen-size rules are on)."""
        state = super().initialize_state(scene_scale, scene_center)
        state["gsplat"] = self.gsplat_strategy().initialize_state(scene_scale=float(scene_scale))
        return state

    def step_pre_backward(
        self, params: Params, optimizers: Optimizers, state: dict[str, Any], step: int, view: ViewObservation
    ) -> None:
        """Keep the gradient of the view's 2D means (gsplat: ``retain_grad``)."""
        view.keep_gradient("gsplat's DefaultStrategy")

    def post_backward(self, ctx: StepContext) -> dict[str, int]:
        counts = {"cloned": 0, "split": 0, "pruned": 0, "opacity_reset": 0}
        if ctx.step >= self.refine_stop_iter:  # gsplat returns at once
            return counts
        params = ctx.params
        strategy = self.gsplat_strategy()
        info = gsplat_info(ctx.views)
        opacities_before = params["opacities"]
        # gsplat draws random numbers (its split) only at refinement steps
        refines = ctx.step > self.refine_start_iter and ctx.step % self.refine_every == 0
        rng = global_rng_is(ctx.rng("gsplat's DefaultStrategy")) if refines else contextlib.nullcontext()
        with rng:
            strategy.step_post_backward(params, ctx.optimizers, ctx.state["gsplat"], ctx.step, info, packed=False)
        counts.update(strategy.counts)
        unchanged = strategy.opacities_after_refine if strategy.opacities_after_refine is not None else opacities_before
        counts["opacity_reset"] = int(params["opacities"] is not unchanged)
        return counts


@dataclass
class GsplatMCMCStrategy(GsplatStrategy):
    """gsplat 1.5.3's MCMCStrategy (3DGS-MCMC: relocation, 5% growth, noise) run inside eg-train."""

    GSPLAT_CLASS = "MCMCStrategy"

    cap_max: int | None = 1_000_000
    """Largest number of Gaussians (gsplat's default; our CPU `mcmc` uses 30 000)."""
    noise_lr: float = 5e5
    """Position noise scale: the noise is lr x noise_lr x gated covariance-shaped Gaussian noise."""
    min_opacity: float = 0.005
    """Gaussians at or below this opacity are dead and get relocated."""
    opacity_reg: float = 0.01
    """Weight of the L1 opacity regulariser (gsplat's simple_trainer mcmc preset; a trainer
    setting there, the strategy's regularization_loss here)."""
    scale_reg: float = 0.01
    """Weight of the L1 scale regulariser (simple_trainer mcmc preset)."""

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.cap_max is None:
            raise StrategyError("gsplat's MCMCStrategy needs cap_max")
        if not 0.0 < self.min_opacity < 1.0:
            raise StrategyError(f"min_opacity must be in (0, 1), got {self.min_opacity}")
        if self.opacity_reg < 0 or self.scale_reg < 0 or self.noise_lr < 0:
            raise StrategyError("opacity_reg, scale_reg and noise_lr must be >= 0")

    def schedule_defaults(self, schedule: Schedule) -> dict[str, int]:
        defaults = super().schedule_defaults(schedule)
        defaults["refine_stop_iter"] = int(math.floor(MCMC_STOP_FRACTION * schedule.max_steps))
        return defaults

    def gsplat_strategy(self) -> Any:
        strategy = _counting_classes()[1](**self.gsplat_fields())
        strategy.counts = {}
        return strategy

    def initialize_state(self, scene_scale: float = 1.0, scene_center: Tensor | None = None) -> dict[str, Any]:
        """Our state plus gsplat's under ``gsplat`` (``binoms``, gsplat's [51, 51] table)."""
        state = super().initialize_state(scene_scale, scene_center)
        state["gsplat"] = self.gsplat_strategy().initialize_state()
        return state

    def regularization_loss(self, params: Params) -> Tensor:
        """opacity_reg * mean(sigmoid(o)) + scale_reg * mean(exp(s)), the rule of our MCMC
        (simple_trainer adds the same terms in its loss)."""
        return MCMCStrategy.regularization_loss(self, params)  # type: ignore[arg-type]

    def post_backward(self, ctx: StepContext) -> dict[str, int]:
        params = ctx.params
        lr = ctx.lr
        if not (math.isfinite(lr) and lr > 0.0):
            raise StrategyError(f"gsplat's MCMCStrategy scales its noise by the means learning rate: pass lr > 0, got {lr}")
        strategy = self.gsplat_strategy()
        device = params["means"].device
        # gsplat draws on every step (its noise)
        with global_rng_is(ctx.rng("gsplat's MCMCStrategy")), cpu_stand_ins(device):
            strategy.step_post_backward(params, ctx.optimizers, ctx.state["gsplat"], ctx.step, {}, lr=lr)
        return {"relocated": strategy.counts.get("relocated", 0), "added": strategy.counts.get("added", 0),
                "perturbed": num_gaussians(params)}
