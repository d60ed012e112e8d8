"""Synthetic Gaussian scenes for benchmarks and tests."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from exploregs_plugin.cameras import Camera


@dataclass
class GaussianScene:
    """Activated Gaussian parameters and one camera (identity pose, looking down +z)."""

    means: Tensor
    """[N, 3] world positions."""
    quats: Tensor
    """[N, 4] wxyz, unnormalised."""
    scales: Tensor
    """[N, 3] activated scales (world units)."""
    opacities: Tensor
    """[N] activated opacities."""
    sh_coeffs: Tensor
    """[N, K, 3] SH coefficients."""
    viewmat: Tensor
    """[4, 4] world-to-camera."""
    K: Tensor
    """[3, 3] intrinsics."""
    width: int
    height: int

    @property
    def camera(self) -> Camera:
        return Camera(self.viewmat, self.K, self.width, self.height)

    def args(self) -> tuple:
        """Positional arguments of ``rasterize``."""
        return (self.means, self.quats, self.scales, self.opacities, self.sh_coeffs, self.camera)

    def to(self, dtype: torch.dtype) -> "GaussianScene":
        f = lambda t: t.detach().to(dtype)  # noqa: E731
        return GaussianScene(f(self.means), f(self.quats), f(self.scales), f(self.opacities), f(self.sh_coeffs),
                             f(self.viewmat), f(self.K), self.width, self.height)  # fmt: skip


def random_scene(
    n: int,
    width: int,
    height: int,
    generator: torch.Generator,
    *,
    depth_range: tuple[float, float] = (2.0, 6.0),
    scale_range: tuple[float, float] = (0.005, 0.05),
    sh_degree: int = 3,
    focal: float | None = None,
    dtype: torch.dtype = torch.float32,
) -> GaussianScene:
    """Random Gaussians inside the view frustum of an identity camera with fx = fy = ``focal``
    (default: ``width``), principal point at the image centre: depths uniform in
    ``depth_range``, log-uniform scales in ``scale_range``, random rotations, opacity
    sigmoid(N(0, 1)), SH coefficients N(0, 0.3^2) (DC N(0, 1))."""
    f = float(width if focal is None else focal)
    g = generator
    z = depth_range[0] + (depth_range[1] - depth_range[0]) * torch.rand(n, generator=g, dtype=torch.float64)
    u = torch.rand(n, generator=g, dtype=torch.float64) * width
    v = torch.rand(n, generator=g, dtype=torch.float64) * height
    means = torch.stack([(u - width / 2) / f * z, (v - height / 2) / f * z, z], -1)
    lo, hi = torch.log(torch.tensor(scale_range, dtype=torch.float64))
    scales = torch.exp(lo + (hi - lo) * torch.rand(n, 3, generator=g, dtype=torch.float64))
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    opacities = torch.sigmoid(torch.randn(n, generator=g, dtype=torch.float64))
    k = (sh_degree + 1) ** 2
    sh = 0.3 * torch.randn(n, k, 3, generator=g, dtype=torch.float64)
    sh[:, 0] = torch.randn(n, 3, generator=g, dtype=torch.float64)
    K = torch.tensor([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]], dtype=torch.float64)
    scene = GaussianScene(means, quats, scales, opacities, sh, torch.eye(4, dtype=torch.float64), K, width, height)
    return scene.to(dtype)
