"""The method registry: named, complete TrainerConfigs, built-in and from installed plugins.

A third-party package adds a method by declaring, in its pyproject.toml::

    [project.entry-points."exploregs.methods"]
    my-method = "my_package.methods:my_method"

where ``my_method`` is a :class:`MethodSpecification`. It then appears in ``eg-train --help``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, fields, replace
from importlib.metadata import entry_points
from typing import TypeVar

from exploregs_plugin.data import DataManagerConfig
from exploregs_plugin.model import GaussianModelConfig
from exploregs_plugin.model.dynamic import DynamicGaussianModelConfig
from exploregs_plugin.engine.pipeline import PipelineConfig
from exploregs_plugin.schedule import ScheduleConfig
from exploregs_plugin.engine.trainer import TrainerConfig

METHOD_ENTRY_POINT_GROUP = "exploregs.methods"


@dataclass(frozen=True)
class MethodSpecification:
    """A method: a complete training config and a one-line description."""

    config: TrainerConfig
    description: str


class MethodRegistryError(ValueError):
    """A method name is unknown, or a plugin's method could not be loaded."""


def _method(name: str, description: str, strategy: object) -> MethodSpecification:
    """A static method: the default model and renderer (the pipeline asks the renderer for what
    the strategy requires)."""
    config = TrainerConfig(method_name=name, pipeline=PipelineConfig(strategy=strategy, model=GaussianModelConfig()))
    return MethodSpecification(config=config, description=description)


DYNAMIC_STEPS = 2000
"""Steps of the dynamic methods: a 10% static warm-up, then the deformation (docs/dynamic.md)."""
DYNAMIC_SCHEDULE = ScheduleConfig(refine_every_frac=0.1, reset_every_frac=1.0)
"""Densify every 200 steps until half the run (four densifications): the set grows by about 1.5x
at every densification, most of it chasing motion (measured: 2.5k -> 39k Gaussians after seven
densifications 100 steps apart; 15.3k after these four, docs/dynamic.md). No opacity reset, as
4DGS on DyNeRF (its reset interval, 60k steps, is longer than its run)."""
DYNAMIC_N_SPLIT = 5
"""Random splits per step in the paper's 4DGS experiment (sparser than its static 20)."""


def _dynamic_method(name: str, description: str, strategy: object) -> MethodSpecification:
    """A 4DGS method: canonical Gaussians + a HexPlane deformation field, on the built-in dynamic scene."""
    pipeline = PipelineConfig(strategy=strategy, model=DynamicGaussianModelConfig(),
                              datamanager=DataManagerConfig(data="builtin:dynamic"))
    config = TrainerConfig(method_name=name, pipeline=pipeline, max_steps=DYNAMIC_STEPS, schedule=DYNAMIC_SCHEDULE)
    return MethodSpecification(config=config, description=description)


def builtin_methods() -> dict[str, MethodSpecification]:
    from exploregs_plugin import strategies as s

    # The paper's absolute budgets (20 random splits every step, 20 seeds per densification)
    # assume 30k steps and millions of Gaussians; the built-in methods use the CPU preset that
    # keeps the paper's explored-to-final ratios for about 20k final Gaussians.
    budget = "cpu-small"
    methods = [
        _method("exploregs-default", "3DGS adaptive density control (clone, split, prune), the baseline.",
                s.DefaultStrategy()),
        _method("exploregs-seed", "Default + Random Seeding: new Gaussians uniform in the bounding box (far side).",
                s.SeedingStrategy(budget=budget)),
        _method("exploregs-split", "Default + Random Splitting: scale-weighted splits regardless of gradient (near side).",
                s.SplittingStrategy(budget=budget)),
        _method("exploregs-seedsplit", "Default + Random Seeding + Random Splitting: both Blur-Trap remedies.",
                s.SeedSplitStrategy(budget=budget)),
        _method("exploregs-ray", "Default + MCMC-style position noise along the viewing ray only (depth exploration).",
                s.RayPerturbationStrategy()),
        _method("exploregs-mcmc", "3DGS-MCMC: relocation of dead Gaussians, 5% growth to a cap, isotropic noise.",
                s.MCMCStrategy()),
        _method("exploregs-mcmc-ray", "3DGS-MCMC with its position noise projected onto the viewing ray.",
                s.MCMCStrategy(noise=s.PositionNoise(mode="ray"))),
        _method("exploregs-mcmc-explore", "3DGS-MCMC whose relocation and growth explore: size-weighted "
                "random splits (or a share, and uniform or guided seeds).", s.MCMCExploreStrategy()),
        _method("exploregs-guided", "Default + guided seeding: seeds on the rays of the pixels with the highest recent error.",
                s.GuidedSeedingStrategy(budget=budget)),
        _method("exploregs-occlusion", "Default + occlusion-aware splitting: split what blending hides and still errs.",
                s.OcclusionSplittingStrategy(budget=budget)),
        _method("exploregs-guided-occlusion", "Default + guided seeding + occlusion-aware splitting.",
                s.GuidedOcclusionStrategy(budget=budget)),
        # Dynamic scenes (4DGS): the paper's sparse Random Splitting, 5 per step, and 20 seeds per densification.
        _dynamic_method("exploregs-4d-default", "4DGS (HexPlane deformation of canonical Gaussians) with 3DGS density control.",
                        s.DefaultStrategy()),
        _dynamic_method("exploregs-4d-split", "4DGS + Random Splitting (5 per step, as the paper's 4DGS experiment).",
                        s.SplittingStrategy(splitting=s.RandomSplitting(n_split=DYNAMIC_N_SPLIT, every=1))),
        _dynamic_method("exploregs-4d-seedsplit", "4DGS + Random Seeding (20 per densification) + Random Splitting (5 per step).",
                        s.SeedSplitStrategy(splitting=s.RandomSplitting(n_split=DYNAMIC_N_SPLIT, every=1),
                                            budget="paper")),
    ]
    return {m.config.method_name: m for m in methods}


def plugin_methods() -> dict[str, MethodSpecification]:
    """Methods declared by other installed packages under ``exploregs.methods``."""
    found: dict[str, MethodSpecification] = {}
    for ep in entry_points(group=METHOD_ENTRY_POINT_GROUP):
        try:
            spec = ep.load()
        except Exception as err:  # a broken plugin must not hide the others
            raise MethodRegistryError(f"method plugin {ep.name!r} ({ep.value}) failed to load: {err}") from err
        if not isinstance(spec, MethodSpecification):
            raise MethodRegistryError(
                f"method plugin {ep.name!r} ({ep.value}) is a {type(spec).__name__}, not a MethodSpecification"
            )
        found[ep.name] = MethodSpecification(replace(spec.config, method_name=ep.name), spec.description)
    return found


def all_methods() -> dict[str, MethodSpecification]:
    methods = builtin_methods()
    for name, spec in plugin_methods().items():
        if name in methods:
            raise MethodRegistryError(f"method plugin {name!r} clashes with a built-in method of that name")
        methods[name] = spec
    return methods


def get_method(name: str) -> MethodSpecification:
    methods = all_methods()
    if name not in methods:
        raise MethodRegistryError(f"unknown method {name!r}; known methods: {', '.join(sorted(methods))}")
    return methods[name]


def strategy_choice(argv: list[str]) -> tuple[list[str], str | None]:
    """``argv`` without ``--strategy NAME`` (or ``--strategy=NAME``), and NAME (None if absent).
    ``--strategy.FIELD`` options stay: they set fields of the chosen strategy. Used by eg-train
    and by the bench's overrides, so both read the flag the same way."""
    from exploregs_plugin.strategies.registry import available_strategies

    rest, name = [], None
    args = iter(argv)
    for arg in args:
        if arg == "--strategy":
            name = next(args, None)
            if name is None or name.startswith("-"):
                raise MethodRegistryError("--strategy needs the name of a registered strategy: "
                                          + ", ".join(sorted(available_strategies())))
        elif arg.startswith("--strategy="):
            name = arg.split("=", 1)[1]
        else:
            rest.append(arg)
    return rest, name


def chosen_strategy(name: str, methods: dict[str, MethodSpecification]) -> object:
    """The strategy ``--strategy NAME`` selects: a built-in with the settings of the method
    ``exploregs-NAME`` when it has that class (so ``eg-train exploregs-default --strategy
    seedsplit`` explores as ``exploregs-seedsplit`` does), otherwise the class's own defaults
    (a plugin's, from the ``exploregs.strategies`` entry points). MethodRegistryError for an
    unknown name or a broken strategy entry point."""
    from exploregs_plugin.strategies.registry import StrategyPluginError, available_strategies

    try:
        registered = available_strategies()
    except StrategyPluginError as err:
        raise MethodRegistryError(str(err)) from err
    if name not in registered:
        raise MethodRegistryError(f"unknown strategy {name!r}; registered strategies: {', '.join(sorted(registered))}")
    cls = registered[name]
    method = methods.get(f"exploregs-{name}")
    if method is not None and type(method.config.pipeline.strategy) is cls:
        return method.config.pipeline.strategy
    return cls()


def with_strategy(config: TrainerConfig, name: str | None, methods: dict[str, MethodSpecification]) -> TrainerConfig:
    """``config`` with the strategy ``--strategy NAME`` selects (unchanged for None)."""
    if name is None:
        return config
    return replace(config, pipeline=replace(config.pipeline, strategy=chosen_strategy(name, methods)))


ConfigT = TypeVar("ConfigT")


def as_variant(cls: type[ConfigT], config: object, **changes: object) -> ConfigT:
    """``config``'s field values in ``cls``, a subclass of its config class that an experiment adds
    fields or behaviour to (the new fields keep their defaults unless ``changes`` sets them)."""
    return cls(**{**{f.name: getattr(config, f.name) for f in fields(config) if f.init}, **changes})


def default_variant(attribute: str, name: str, description: str,
                    variant: Callable[[TrainerConfig], TrainerConfig]) -> Callable[[str], MethodSpecification]:
    """A module ``__getattr__`` whose ``attribute`` is the entry point of the method ``name``:
    exploregs-default's config changed by ``variant`` (an experiment's variant of a core part),
    any strategy with ``--strategy NAME``. The method is made when the registry first loads the
    entry point, from the built-in exploregs-default as it is then, and kept."""
    made: list[MethodSpecification] = []

    def __getattr__(requested: str) -> MethodSpecification:
        if requested != attribute:
            raise AttributeError(f"module has no attribute {requested!r}")
        if not made:
            config = variant(builtin_methods()["exploregs-default"].config)
            made.append(MethodSpecification(config=replace(config, method_name=name), description=description))
        return made[0]

    return __getattr__
