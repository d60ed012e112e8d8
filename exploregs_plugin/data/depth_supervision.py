"""Depth maps for the depth loss, degraded to play a monocular estimate: noise + smooth bias.

A monocular depth network is locally noisy and wrong by a smooth, relative factor. With d the
ground-truth map, the supervised map is

    d' = d (1 + b B(x, y) + s n(x, y)),   n ~ N(0, 1) per pixel,

where B is a smooth field of unit RMS (a sum of random plane waves whose wavelength is a fraction
of the image size), b = ``bias_amplitude`` and s = ``noise_std``. Both are relative to depth.
The degradation of a view depends only on (seed, view index): the same view always gets the same
map, as a fixed estimate computed once per image would.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from PIL import Image
from torch import Tensor

from .errors import DataError

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


def read_depth_map(path: Path, size: tuple[int, int]) -> tuple[np.ndarray, tuple[int, int]]:
    """(float32 [H, W] depth resized (nearest) to ``size`` = (width, height), (masked pixels,
    pixels in the file)).

    Non-finite values (sky stored as inf, holes as NaN) mean "no depth here", as in depth
    datasets: they become 0, which the depth loss leaves out with every value <= 0. DataError
    for a file that is unreadable or not a 2D array.
    """
    try:
        depth = np.load(path)
    except (OSError, ValueError) as err:
        raise DataError(path, f"depth file is unreadable ({err})") from err
    if depth.ndim != 2 or depth.dtype.kind not in "fiu":
        raise DataError(path, f"depth must be a numeric [H, W] array, got shape {depth.shape} of {depth.dtype}")
    depth = depth.astype(np.float32)
    finite = np.isfinite(depth)
    masked = int(depth.size - np.count_nonzero(finite))
    if masked:
        depth = np.where(finite, depth, np.float32(0.0))
    if depth.shape != (size[1], size[0]):
        depth = np.asarray(Image.fromarray(depth).resize(size, Image.Resampling.NEAREST))
    return depth, (masked, int(finite.size))


def warn_masked_depth(masked: dict[Path, tuple[int, int]]) -> None:
    """One warning for every depth map with non-finite pixels: ``masked`` maps a depth file to
    (masked pixels, pixels in the file)."""
    hit = {path: counts for path, counts in masked.items() if counts[0]}
    if not hit:
        return
    pixels = sum(c[0] for c in hit.values())
    total = sum(c[1] for c in masked.values())
    folders = sorted({str(path.parent) for path in hit})
    example = ", ".join(path.name for path in list(hit)[:3])
    warnings.warn(f"{', '.join(folders)}: {pixels} of {total} depth pixels ({100 * pixels / total:.2f}%) in "
                  f"{len(hit)} of {len(masked)} depth maps are not finite (inf or NaN, e.g. sky) and are masked "
                  f"as no depth (e.g. {example})", stacklevel=3)
