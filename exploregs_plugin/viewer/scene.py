"""What the viewer shows, independent of where it comes from (a training pipeline, a finished
run, a PLY file, a test)."""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from torch import Tensor

from exploregs_plugin.cameras import Camera
from exploregs_plugin.rasterizer import RasterSettings
from exploregs_plugin.viewer.display import available_sh_degree


@dataclass
class ViewerScene:
    """Sources of everything the viewer draws.

    params: returns the *current* raw Gaussian parameters (called only at step boundaries by
    the thread that owns them; the pipeline replaces its tensors when the set changes, so the
    viewer must not keep a reference).
    cameras: training cameras, drawn as frustums. thumbnail(i): image [H, W, 3] in [0, 1] of
    camera i (None: frustums without images). points [P, 3], points_rgb [P, 3] in [0, 1]:
    initial point cloud (None: none). background [3] in [0, 1]. extent: scene radius (sizes
    of frustums and points scale with it).
    """

    params: Callable[[], Mapping[str, Tensor]]
    max_sh_degree: int
    cameras: Sequence[Camera] = ()
    thumbnail: Callable[[int], Tensor] | None = None
    points: Tensor | None = None
    points_rgb: Tensor | None = None
    background: Tensor = field(default_factory=lambda: torch.zeros(3))
    extent: float = 1.0
    raster_settings: RasterSettings | None = None
    name: str = "scene"
    step: int = 0
    deformation: Callable[[], Any] | None = None
    """A dynamic scene's deformation field, read like ``params`` (None: a static scene); the GUI
    then has a time slider."""

    def __post_init__(self) -> None:
        if not 0 <= self.max_sh_degree <= 3:
            raise ValueError(f"viewer scene max_sh_degree must be in 0..3, got {self.max_sh_degree}")
        if not (math.isfinite(self.extent) and self.extent > 0.0):
            raise ValueError(f"viewer scene extent must be positive and finite, got {self.extent}")
        if self.points is not None and (self.points.ndim != 2 or self.points.shape[1] != 3):
            raise ValueError(f"viewer scene points must be [P, 3], got {tuple(self.points.shape)}")
        if self.points is not None and self.points_rgb is not None and self.points_rgb.shape != self.points.shape:
            raise ValueError(
                f"viewer scene points_rgb {tuple(self.points_rgb.shape)} does not match points {tuple(self.points.shape)}"
            )
        if tuple(self.background.shape) != (3,):
            raise ValueError(f"viewer scene background must be [3], got {tuple(self.background.shape)}")

    @classmethod
    def from_pipeline(cls, pipeline: Any, step: int = 0) -> "ViewerScene":
        """The scene of a training (or loaded) ``Pipeline``: its live parameters, its
        datamanager's training cameras, images, initial points and background."""
        dm = pipeline.datamanager

        def thumbnail(i: int) -> Tensor:
            return dm.train_item(i)[1]

        return cls(
            params=lambda: pipeline.params,
            max_sh_degree=int(pipeline.model.config.sh_degree),
            cameras=list(dm.train_cameras),
            thumbnail=thumbnail,
            points=dm.points,
            points_rgb=dm.points_rgb,
            background=torch.as_tensor(dm.background, dtype=torch.float32),
            extent=float(dm.scene_extent),
            raster_settings=pipeline.model.config.raster,
            name=str(dm.scene_name),
            step=step,
            deformation=(lambda: pipeline.model.deformation) if pipeline.model.parts else None,
        )

    @classmethod
    def from_params(
        cls,
        params: Mapping[str, Tensor],
        cameras: Sequence[Camera] = (),
        background: Tensor | None = None,
        name: str = "scene",
        step: int = 0,
    ) -> "ViewerScene":
        """A fixed Gaussian set (e.g. read from a PLY); the extent is measured from the means
        (and cameras) so that frustums and points get a sensible size."""
        fixed = dict(params)
        return cls(
            params=lambda: fixed,
            max_sh_degree=available_sh_degree(fixed),
            cameras=list(cameras),
            background=torch.zeros(3) if background is None else background.float(),
            extent=measured_extent(fixed["means"], cameras),
            name=name,
            step=step,
        )


def measured_extent(means: Tensor, cameras: Sequence[Camera] = ()) -> float:
    """Robust radius of the scene: the 90th percentile distance of the means (and camera
    centres) from their median, floored at 1e-3 so sizes derived from it stay positive."""
    pts = [means.detach().float().reshape(-1, 3)]
    pts += [c.camera_center.detach().float().reshape(1, 3) for c in cameras]
    cloud = torch.cat(pts)
    cloud = cloud[torch.isfinite(cloud).all(dim=1)]
    if cloud.shape[0] == 0:
        return 1.0
    centre = cloud.median(dim=0).values
    dist = (cloud - centre).norm(dim=1)
    return max(float(torch.quantile(dist, 0.9)) if dist.numel() > 1 else float(dist.max()), 1e-3)


def scene_centre(scene: ViewerScene) -> np.ndarray:
    """A point to look at: the median of the initial points, else of the current means, else
    the origin. [3]"""
    for cloud in (scene.points, scene.params().get("means")):
        if cloud is not None and cloud.shape[0] > 0:
            finite = cloud.detach().float()
            finite = finite[torch.isfinite(finite).all(dim=1)]
            if finite.shape[0] > 0:
                return finite.median(dim=0).values.double().cpu().numpy()
    return np.zeros(3)
