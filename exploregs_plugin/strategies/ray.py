"""Default + ray perturbation: 3DGS ADC with depth-only exploration noise after each step."""

from __future__ import annotations

from dataclasses import dataclass

from .default import DefaultStrategy
from .perturbation import RayPerturbationMixin


@dataclass
class RayPerturbationStrategy(RayPerturbationMixin, DefaultStrategy):
    """3DGS adaptive density control plus MCMC-style noise projected onto the camera ray."""
