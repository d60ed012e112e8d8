"""Default + ray perturbation: 3DGS ADC with depth-only exploration noise after each step."""

from __future__ import annotations

from dataclasses import dataclass, field

from .exploration import ExplorationStrategy
from .position_noise import PositionNoise


@dataclass
class RayPerturbationStrategy(ExplorationStrategy):
    """3DGS adaptive density control plus MCMC-style noise projected onto the camera ray."""

    noise: PositionNoise = field(default_factory=lambda: PositionNoise(mode="ray"))
    """The position noise, along the ray by default."""
