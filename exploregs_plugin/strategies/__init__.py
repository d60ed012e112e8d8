"""Densification and exploration strategies; every change to the Gaussian set goes via ``ops``."""

from . import ops
from .base import StepContext, Strategy, StrategyError
from .budget import BUDGET_PRESETS, ExplorationBudget, resolve_budget, scaled_budget
from .default import DefaultStrategy
from .mcmc import MCMCStrategy
from .perturbation import NoiseMixin, RayPerturbationMixin, position_noise
from .ray import RayPerturbationStrategy
from .registry import ENTRY_POINT_GROUP, StrategyPluginError, available_strategies, builtin_strategies
from .guided import GuidedSeedingMixin, GuidedSeedingStrategy
from .occlusion import GuidedOcclusionStrategy, OcclusionSplittingMixin, OcclusionSplittingStrategy
from .seeding import SeedingMixin, SeedingStrategy
from .seedsplit import SeedSplitStrategy
from .splitting import SplittingMixin, SplittingStrategy

__all__ = [
    "BUDGET_PRESETS",
    "ENTRY_POINT_GROUP",
    "DefaultStrategy",
    "ExplorationBudget",
    "GuidedOcclusionStrategy",
    "GuidedSeedingMixin",
    "GuidedSeedingStrategy",
    "MCMCStrategy",
    "NoiseMixin",
    "OcclusionSplittingMixin",
    "OcclusionSplittingStrategy",
    "RayPerturbationMixin",
    "RayPerturbationStrategy",
    "SeedSplitStrategy",
    "SeedingMixin",
    "SeedingStrategy",
    "SplittingMixin",
    "SplittingStrategy",
    "StepContext",
    "Strategy",
    "StrategyError",
    "StrategyPluginError",
    "available_strategies",
    "builtin_strategies",
    "ops",
    "position_noise",
    "resolve_budget",
    "scaled_budget",
]
