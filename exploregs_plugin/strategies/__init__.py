"""Densification and exploration strategies; every change to the Gaussian set goes via ``row_ops``."""

from . import row_ops
from .base import StepContext, Strategy, StrategyError
from .budget import BUDGET_PRESETS, ExplorationBudget, resolve_budget, scaled_budget
from .default import DefaultStrategy
from .exploration import ExplorationStrategy
from .mcmc import MCMCStrategy
from .mcmc_explore import MCMCExploreStrategy
from .operator_contract import Operator
from .position_noise import PositionNoise, position_noise
from .ray_perturbation import RayPerturbationStrategy
from .registry import ENTRY_POINT_GROUP, StrategyPluginError, available_strategies, builtin_strategies
from .guided import GuidedSeeding, GuidedSeedingStrategy
from .occlusion import GuidedOcclusionStrategy, OcclusionSplitting, OcclusionSplittingStrategy
from .seeding import RandomSeeding, SeedingStrategy
from .seedsplit import SeedSplitStrategy
from .splitting import RandomSplitting, SplittingStrategy

__all__ = [
    "BUDGET_PRESETS",
    "ENTRY_POINT_GROUP",
    "DefaultStrategy",
    "ExplorationBudget",
    "ExplorationStrategy",
    "GuidedOcclusionStrategy",
    "GuidedSeeding",
    "GuidedSeedingStrategy",
    "MCMCExploreStrategy",
    "MCMCStrategy",
    "OcclusionSplitting",
    "OcclusionSplittingStrategy",
    "Operator",
    "PositionNoise",
    "RandomSeeding",
    "RandomSplitting",
    "RayPerturbationStrategy",
    "SeedSplitStrategy",
    "SeedingStrategy",
    "SplittingStrategy",
    "StepContext",
    "Strategy",
    "StrategyError",
    "StrategyPluginError",
    "available_strategies",
    "builtin_strategies",
    "row_ops",
    "position_noise",
    "resolve_budget",
    "scaled_budget",
]
