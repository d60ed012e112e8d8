"""Seed+Split: Random Seeding and Random Splitting together, by composition.

Neither operator is copied: the strategy holds both, in the order they run. On a step where both
fire, Random Splitting runs first, then seeds are added (fresh seeds are not split in the step
that creates them).
"""

from __future__ import annotations

from dataclasses import dataclass, field

from .exploration import ExplorationStrategy
from .seeding import RandomSeeding
from .splitting import RandomSplitting


@dataclass
class SeedSplitStrategy(ExplorationStrategy):
    """Random Seeding (far side) + Random Splitting (near side) on top of 3DGS ADC."""

    splitting: RandomSplitting = field(default_factory=RandomSplitting)
    """Random Splitting (near side), run first."""
    seeding: RandomSeeding = field(default_factory=RandomSeeding)
    """Random Seeding (far side), run after the splits."""
