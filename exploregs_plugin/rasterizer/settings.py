"""Named constants of the 3DGS image model and the compositor's work-size knob."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal


VISIBILITY_COLUMNS = ("weight", "alpha", "peak")
"""The columns of a render's ``info["visibility"]`` [N, 3]: over the view's pixels, the summed
compositing weight w = alpha T, the summed alpha, and the largest w (the peak: a Gaussian that
paints one pixel on its own has a peak near 1 however few pixels it covers)."""
VISIBILITY_PEAK = VISIBILITY_COLUMNS.index("peak")
"""The peak's column. The columns before it add up over pixels, tiles and views; the peak takes the
largest (:func:`exploregs_plugin.rasterizer.composite.add_visibility_`, the compiled ``sum_pairs``)."""


@dataclass(frozen=True)
class RasterSettings:
    """Constants of the 3D Gaussian Splatting image model (defaults = the original renderer)."""

    backend: Literal["auto", "torch", "cpp", "gsplat"] = "auto"
    """Renderer: 'cpp' (compiled CPU compositor, built on first use), 'gsplat' (gsplat's CUDA
    kernels; --device cuda and the gpu extra), 'torch' (the pure-torch reference, any device), or
    'auto': gsplat on CUDA when installed, cpp on the CPU when it builds, else torch."""

    eps2d: float = 0.3
    """Low-pass filter in pixels^2 added to the diagonal of every 2D covariance."""
    sigma_radius: float = 3.0
    """Support half-width in standard deviations: radius = ceil(sigma_radius * sigma) per axis."""
    guard_band: float = 0.3
    """Extra fraction of tan(fov/2) beyond the image edge at which x/z and y/z are clamped in the Jacobian."""
    alpha_max: float = 0.99
    """Upper clamp of a pair's alpha (keeps 1 - alpha >= 0.01, so transmittance stays invertible)."""
    alpha_min: float = 1.0 / 255.0
    """Pairs whose alpha is below this are skipped (contribute nothing)."""
    transmittance_min: float = 1e-4
    """A Gaussian that would bring transmittance below this is left out and compositing stops."""
    tile_size: int = 16
    """Side of the square screen tiles in pixels."""
    antialiased: bool = False
    """Scale opacity by sqrt(det(cov2d) / det(cov2d + eps2d I)) (the anti-aliased 3DGS variant)."""
    chunk_elements: int = 1 << 18
    """Target pixel x pair count of one compositing chunk on the CPU (keeps temporaries cache-sized)."""
    gpu_chunk_elements: int = 1 << 25
    """The same on a GPU, where few large kernels beat many small ones (a chunk's temporaries
    take about 20 bytes per element: 1 << 25 is about 0.7 GB)."""
    single_threaded_backward: bool = True
    """Run the backward pass of a render (projection included) with single-threaded torch ops;
    the compositor still uses ``workers`` threads. Faster on small shared machines."""
    visibility_stats: bool = False
    """Also return, per Gaussian, the sums over pixels of its compositing weight alpha T and of
    its alpha, and its largest weight at any pixel (info["visibility"] [N, 3], the columns of
    ``VISIBILITY_COLUMNS``; occlusion-aware splitting and the significance cuts read them). Costs
    one more accumulation per pixel in the forward."""
    absgrad: bool = False
    """Also sum, per Gaussian and axis, the absolute values of each pixel's dL/d(mean2d) in the
    backward (AbsGS; gsplat's ``absgrad``), left on ``info["means2d"].absgrad`` [N, 2] in pixels
    after ``loss.backward()``: where the pixels pull a Gaussian's centre in opposite directions
    (a blur over texture) the gradient cancels and these sums do not. Costs two more
    accumulations per pixel in the backward."""
    workers: int = 0
    """Compositing threads, each running single-threaded torch ops on its own chunks (0 = the
    caller's torch thread count, which eg-train's --num-threads sets). Results agree across
    settings up to float rounding."""

    def __post_init__(self) -> None:
        if not 0.0 < self.alpha_min < self.alpha_max < 1.0:
            raise ValueError(
                f"RasterSettings: need 0 < alpha_min < alpha_max < 1, got alpha_min={self.alpha_min}, "
                f"alpha_max={self.alpha_max}"
            )
        if not 0.0 <= self.transmittance_min < 1.0:
            raise ValueError(f"RasterSettings.transmittance_min must be in [0, 1), got {self.transmittance_min}")
        if self.tile_size < 1 or self.chunk_elements < 1 or self.gpu_chunk_elements < 1 or self.workers < 0:
            raise ValueError(
                f"RasterSettings: tile_size, chunk_elements must be >= 1 and workers >= 0, got "
                f"{self.tile_size}, {self.chunk_elements}, {self.workers}"
            )
        if self.eps2d < 0.0 or self.sigma_radius <= 0.0 or self.guard_band < 0.0:
            raise ValueError("RasterSettings: eps2d and guard_band must be >= 0 and sigma_radius > 0")
