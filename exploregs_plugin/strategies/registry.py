"""Strategy registry: built-in strategies plus those other packages declare as entry points.

A package registers a strategy class under the entry-point group ``exploregs.strategies``::

    [project.entry-points."exploregs.strategies"]
    my-strategy = "my_package.strategy:MyStrategy"
"""

from __future__ import annotations

import importlib.metadata

from .base import Strategy, StrategyError

ENTRY_POINT_GROUP = "exploregs.strategies"


class StrategyPluginError(StrategyError):
    """An entry point in ``exploregs.strategies`` could not be loaded or is not a strategy."""


def builtin_strategies() -> dict[str, type[Strategy]]:
    """Name -> class of the strategies shipped with ExploreGS."""
    from .default import DefaultStrategy
    from .guided import GuidedSeedingStrategy
    from .mcmc import MCMCStrategy
    from .mcmc_explore import MCMCExploreStrategy
    from .occlusion import GuidedOcclusionStrategy, OcclusionSplittingStrategy
    from .ray_perturbation import RayPerturbationStrategy
    from .seeding import SeedingStrategy
    from .seedsplit import SeedSplitStrategy
    from .splitting import SplittingStrategy

    return {
        "default": DefaultStrategy,
        "seed": SeedingStrategy,
        "split": SplittingStrategy,
        "seedsplit": SeedSplitStrategy,
        "ray": RayPerturbationStrategy,
        "mcmc": MCMCStrategy,
        "mcmc-explore": MCMCExploreStrategy,
        "guided": GuidedSeedingStrategy,
        "occlusion": OcclusionSplittingStrategy,
        "guided-occlusion": GuidedOcclusionStrategy,
    }


def _is_strategy_class(obj: object) -> bool:
    # The pipeline calls every hook of the contract unconditionally; the base class declares
    # each one with a default, so only subclasses are accepted.
    return isinstance(obj, type) and issubclass(obj, Strategy)


def available_strategies() -> dict[str, type[Strategy]]:
    """Built-in strategies merged with every ``exploregs.strategies`` entry point.

    Raises :class:`StrategyPluginError` naming the entry point and its distribution when one
    fails to import, is not a strategy class, or reuses a built-in name.
    """
    strategies: dict[str, type[Strategy]] = dict(builtin_strategies())
    for ep in importlib.metadata.entry_points(group=ENTRY_POINT_GROUP):
        dist = getattr(getattr(ep, "dist", None), "name", None) or "unknown distribution"
        where = f"entry point '{ep.name} = {ep.value}' (group {ENTRY_POINT_GROUP}, from {dist})"
        if ep.name in strategies:
            raise StrategyPluginError(f"{where} reuses the strategy name '{ep.name}', which is taken")
        try:
            obj = ep.load()
        except Exception as err:  # any import-time failure of a third-party module
            raise StrategyPluginError(f"{where} failed to load: {type(err).__name__}: {err}") from err
        if not _is_strategy_class(obj):
            raise StrategyPluginError(
                f"{where} resolved to {obj!r}, which is not a strategy class (subclass "
                f"exploregs_plugin.strategies.Strategy, whose hooks all have defaults)"
            )
        strategies[ep.name] = obj
    return strategies
