"""The paper's branch ablation as a model variant: Default with some position-gradient paths
switched off, registered as the method ``exploregs-branch-ablation`` (``--model.detach-paths``).

A 3D mean reaches the image through three paths (``analysis/branches.py``): the projected 2D
mean (and depth), the 2D covariance through the perspective Jacobian, and the SH view direction.
The rasterizer takes a tensor per path (``means_cov``, ``means_sh``); here each switched-off path
gets a detached copy, so the forward pass is unchanged and only that path's gradient stops. The
core model renders with one ``means`` and knows nothing of this; the method comes in through the
``exploregs.methods`` entry point of the package's own ``pyproject.toml``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import Literal

from torch import Tensor, nn

from exploregs_plugin.cameras import Camera
from exploregs_plugin.method_configs import as_variant, default_variant
from exploregs_plugin.model.gaussians import GaussianModel, GaussianModelConfig, activate
from exploregs_plugin.rasterizer import RasterSettings, rasterize_branched

PositionPath = Literal["mean2d", "cov", "sh"]
POSITION_PATHS: tuple[PositionPath, ...] = ("mean2d", "cov", "sh")


def render_detached(
    params: Mapping[str, Tensor],
    camera: Camera,
    sh_degree: int,
    background: Tensor | None,
    detach_paths: tuple[PositionPath, ...],
    settings: RasterSettings | None = None,
) -> tuple[Tensor, Tensor, Tensor, dict]:
    """``render_params`` with the position paths in ``detach_paths`` switched off.

    Each path gets its own view of the means, so any subset can be detached while the forward
    pass stays identical. A switched-off 2D-mean path still goes through a fresh leaf that
    requires grad: the projected means then keep their screen-space gradient, which is the
    densification statistic, not a position-gradient branch; only its flow into
    ``params["means"]`` is cut."""
    unknown = set(detach_paths) - set(POSITION_PATHS)
    if unknown:
        raise ValueError(f"unknown position paths {sorted(unknown)}; choose from {', '.join(POSITION_PATHS)}")
    means = params["means"]
    means_2d = means.detach().requires_grad_(means.requires_grad) if "mean2d" in detach_paths else means
    means_cov = means.detach() if "cov" in detach_paths else means
    means_sh = means.detach() if "sh" in detach_paths else means
    _, quats, scales, opacities, sh = activate(params)
    return rasterize_branched(means_2d, quats, scales, opacities, sh,
                     camera, sh_degree=sh_degree, background=background, means_cov=means_cov, means_sh=means_sh,
                     settings=settings)


@dataclass
class BranchAblationModelConfig(GaussianModelConfig):
    """The Gaussian model with some position-gradient paths switched off (the branch ablation)."""

    detach_paths: tuple[PositionPath, ...] = ()
    """Position-gradient paths to switch off: mean2d, cov (2D covariance), sh (SH view direction).
    Renders and densification's 2D gradient are unchanged."""

    def setup(self, points: Tensor | None, points_rgb: Tensor | None, seed: int = 0) -> "BranchAblationModel":
        unknown = set(self.detach_paths) - set(POSITION_PATHS)
        if unknown:
            raise ValueError(f"unknown position paths {sorted(unknown)}; choose from {', '.join(POSITION_PATHS)}")
        return BranchAblationModel(self, super().setup(points, points_rgb, seed).params)


class BranchAblationModel(GaussianModel):
    """Renders through :func:`render_detached` with its config's ``detach_paths``."""

    config: BranchAblationModelConfig

    def __init__(self, config: BranchAblationModelConfig, params: nn.ParameterDict) -> None:
        super().__init__(config, params)

    def render(self, camera: Camera, sh_degree: int | None = None, background: Tensor | None = None,
               visibility_stats: bool = False) -> tuple[Tensor, Tensor, Tensor, dict]:
        return render_detached(self.params_at(camera.time), camera,
                               sh_degree if sh_degree is not None else self.config.sh_degree, background,
                               self.config.detach_paths, self.raster_settings(visibility_stats))


__getattr__ = default_variant(
    "branch_ablation_method", "exploregs-branch-ablation",
    "3DGS density control with position-gradient paths switched off (--model.detach-paths; the branch ablation).",
    # all paths on by default
    lambda config: replace(config, pipeline=replace(config.pipeline,
                                                    model=as_variant(BranchAblationModelConfig, config.pipeline.model))),
)
