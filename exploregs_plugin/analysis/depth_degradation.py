"""Degraded depth maps for the depth-supervision experiment: noise + smooth bias, as a monocular
estimate has, and the method that trains with them (``exploregs-mono-depth``).

A monocular depth network is locally noisy and wrong by a smooth, relative factor. With d the
ground-truth map, the supervised map is

    d' = d (1 + b B(x, y) + s n(x, y)),   n ~ N(0, 1) per pixel,

where B is a smooth field of unit RMS (a sum of random plane waves whose wavelength is a fraction
of the image size), b = ``bias_amplitude`` and s = ``noise_std``. Both are relative to depth.
The degradation of a view depends only on (seed, view index): the same view always gets the same
map, as a fixed estimate computed once per image would.

The core loss (``DepthTerm``) reads the dataset's maps as they are; the experiment is a pipeline
variant, :class:`MonoDepthPipelineConfig`, whose depth term degrades them first.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import torch
from torch import Tensor

from exploregs_plugin.engine.loss_terms import DepthTerm, LossTerm, ViewLossInput
from exploregs_plugin.method_configs import as_variant, default_variant
from exploregs_plugin.engine.pipeline import PipelineConfig

N_WAVES = 6  # plane waves in the smooth bias field
MIN_RELATIVE_DEPTH = 0.05  # the degraded depth never drops below this fraction of the truth


@dataclass
class DepthSupervisionConfig:
    """How the dataset's depth maps are degraded before the depth loss uses them."""

    noise_std: float = 0.0
    """Per-pixel Gaussian noise, relative to depth (0.05 = 5%)."""
    bias_amplitude: float = 0.0
    """RMS of the smooth multiplicative bias (0.1 = 10% of depth)."""
    bias_wavelength: float = 0.5
    """Wavelength of the bias field as a fraction of the larger image side."""
    seed: int = 0
    """Seed of the noise and bias (combined with the view index)."""

    def __post_init__(self) -> None:
        if self.noise_std < 0 or self.bias_amplitude < 0:
            raise ValueError(f"depth supervision: noise_std and bias_amplitude must be >= 0, got "
                             f"{self.noise_std}, {self.bias_amplitude}")
        if self.bias_wavelength <= 0:
            raise ValueError(f"depth supervision: bias_wavelength must be > 0, got {self.bias_wavelength}")

    @property
    def active(self) -> bool:
        return self.noise_std > 0 or self.bias_amplitude > 0

    def apply(self, depth: Tensor, view_index: int) -> Tensor:
        """depth: [H, W, 1] (invalid pixels: <= 0 or non-finite, left as they are) -> [H, W, 1]."""
        return degrade_depth(depth, view_index, self) if self.active else depth


def smooth_field(height: int, width: int, wavelength: float, generator: torch.Generator) -> Tensor:
    """A smooth random field of unit RMS: sum of N_WAVES plane waves with random directions and
    phases, wavelength in pixels. Returns [H, W] float32."""
    angles = torch.rand(N_WAVES, generator=generator) * (2 * math.pi)
    phases = torch.rand(N_WAVES, generator=generator) * (2 * math.pi)
    ys, xs = torch.meshgrid(torch.arange(height, dtype=torch.float32), torch.arange(width, dtype=torch.float32),
                            indexing="ij")  # fmt: skip
    k = 2 * math.pi / max(wavelength, 1e-6)
    field = torch.zeros(height, width)
    for a, p in zip(angles.tolist(), phases.tolist()):
        field += torch.cos(k * (math.cos(a) * xs + math.sin(a) * ys) + p)
    # each cosine has RMS 1/sqrt(2); independent phases add in quadrature
    return field / math.sqrt(N_WAVES / 2.0)


def degrade_depth(depth: Tensor, view_index: int, config: DepthSupervisionConfig) -> Tensor:
    """d' = d (1 + b B + s n) on valid pixels (see the module docstring). depth: [H, W, 1]."""
    if depth.dim() != 3 or depth.shape[-1] != 1:
        raise ValueError(f"depth map must have shape [H, W, 1], got {list(depth.shape)}")
    height, width = depth.shape[:2]
    generator = torch.Generator().manual_seed(config.seed * 1_000_003 + int(view_index))
    wavelength = config.bias_wavelength * max(height, width)
    factor = 1.0 + config.bias_amplitude * smooth_field(height, width, wavelength, generator)
    factor = factor + config.noise_std * torch.randn(height, width, generator=generator)
    factor = factor.clamp_min(MIN_RELATIVE_DEPTH)  # a depth map has no negative depths
    valid = torch.isfinite(depth) & (depth > 0)
    return torch.where(valid, depth * factor.to(depth.dtype)[..., None], depth)



@dataclass(frozen=True)
class DegradedDepthTerm(DepthTerm):
    """:class:`DepthTerm` against the dataset's depth map degraded by ``supervision``."""

    supervision: DepthSupervisionConfig = field(default_factory=DepthSupervisionConfig)

    def target(self, view: ViewLossInput) -> Tensor:
        return self.supervision.apply(super().target(view), view.index)


MONO_DEPTH_WEIGHT = 0.1
"""Weight of the depth term in exploregs-mono-depth."""
MONO_DEPTH = DepthSupervisionConfig(noise_std=0.05, bias_amplitude=0.1)
"""exploregs-mono-depth's maps: 5% per-pixel noise and a 10% smooth bias (relative to depth)."""


@dataclass
class MonoDepthPipelineConfig(PipelineConfig):
    """The pipeline with its depth loss against degraded depth maps."""

    depth_supervision: DepthSupervisionConfig = field(default_factory=lambda: replace(MONO_DEPTH))
    """Degrade the depth maps before the depth loss (noise, smooth bias) to play a monocular estimate."""

    def loss_terms(self) -> list[LossTerm]:
        return [DegradedDepthTerm(term.weight, term.space, self.depth_supervision) if type(term) is DepthTerm
                else term for term in super().loss_terms()]


__getattr__ = default_variant(
    "mono_depth_method", "exploregs-mono-depth",
    "3DGS density control with a depth loss against monocular-like depth maps (the dataset's, with noise "
    "and a smooth bias: --depth-supervision.*).",
    lambda config: replace(config, pipeline=as_variant(MonoDepthPipelineConfig, config.pipeline,
                                                       depth_loss_weight=MONO_DEPTH_WEIGHT)),
)
