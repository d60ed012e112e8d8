"""Seed+Split: Random Seeding and Random Splitting together, by composition.

Neither operator is copied: the class only stacks the two mixins in front of Default. On a step
where both fire, Random Splitting runs first, then seeds are added (fresh seeds are not split in
the step that creates them).
"""

from __future__ import annotations

from dataclasses import dataclass

from .default import DefaultStrategy
from .seeding import SeedingMixin
from .splitting import SplittingMixin


@dataclass
class SeedSplitStrategy(SeedingMixin, SplittingMixin, DefaultStrategy):
    """Random Seeding (far side) + Random Splitting (near side) on top of 3DGS ADC."""
