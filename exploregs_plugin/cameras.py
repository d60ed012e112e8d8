"""The camera record shared by data, model, rasterizer wrappers and viewer.

Conventions (docs/architecture.md#conventions): OpenCV axes (x right, y down, z forward), world-to-camera
``viewmat [4, 4]``, pinhole intrinsics ``K [3, 3]``, pixel centres at +0.5.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import torch
from torch import Tensor


@dataclass(frozen=True)
class Camera:
    """One pinhole camera.

    viewmat: [4, 4] world-to-camera (OpenCV axes).
    K: [3, 3] intrinsics in pixels for an image of ``width`` x ``height``.
    """

    viewmat: Tensor
    K: Tensor
    width: int
    height: int
    name: str = ""
    time: float | None = None
    """Normalised time in [0, 1] of a frame of a dynamic scene (None: a static scene's view)."""
    near: float = 0.01
    """Gaussians whose camera depth z is not in (near, far) are not drawn."""
    far: float = 1e10

    @property
    def camera_center(self) -> Tensor:
        """World position of the camera centre: [3] = -R^T t."""
        rot = self.viewmat[:3, :3]
        return -(rot.transpose(0, 1) @ self.viewmat[:3, 3])

    def to(self, *args: Any, **kwargs: Any) -> "Camera":
        """The camera with viewmat and K moved like ``Tensor.to`` (a dtype, a device, or both)."""
        return replace(self, viewmat=self.viewmat.to(*args, **kwargs), K=self.K.to(*args, **kwargs))

    def scaled(self, factor: float, size: tuple[int, int] | None = None) -> "Camera":
        """The same camera for an image resized by ``factor`` (e.g. 0.5 halves each side), or to
        exactly ``size`` = (width, height) when given (each axis by its own ratio)."""
        width = max(1, int(round(self.width * factor))) if size is None else int(size[0])
        height = max(1, int(round(self.height * factor))) if size is None else int(size[1])
        sx, sy = width / self.width, height / self.height
        K = self.K.clone()
        K[0, :] *= sx
        K[1, :] *= sy
        K[2, :] = torch.tensor([0.0, 0.0, 1.0], dtype=K.dtype, device=K.device)
        return replace(self, K=K, width=width, height=height)
