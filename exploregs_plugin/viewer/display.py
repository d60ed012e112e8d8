"""One viewer frame from a snapshot: rgb, alpha (grey) or depth (colour-mapped per frame).

The pictures are made exactly as ``eg-render`` makes them (``exploregs_plugin.io.frames``), so
the viewer and rendered videos agree; the viewer picks the depth range per frame.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from exploregs_plugin.cameras import Camera
from exploregs_plugin.io.frames import colorize_depth, depth_range, to_uint8
from exploregs_plugin.io.ply import sh_degree_for_rest
from exploregs_plugin.model.dynamic import params_at_time
from exploregs_plugin.model.gaussians import render_camera
from exploregs_plugin.rasterizer import RasterSettings
from exploregs_plugin.viewer.outputs import OutputKind
from exploregs_plugin.viewer.snapshot import Snapshot


def available_sh_degree(params: dict[str, Tensor]) -> int:
    """Largest SH degree the coefficients support (shN [N, (d+1)^2 - 1, 3])."""
    return sh_degree_for_rest(3 * int(params["shN"].shape[1]))


def render_frame(
    snapshot: Snapshot,
    camera: Camera,
    output: OutputKind,
    sh_degree: int,
    background: Tensor | None,
    settings: RasterSettings | None = None,
    time: float = 0.0,
) -> np.ndarray:
    """One viewer frame: uint8 [H, W, 3] for ``camera`` (H = camera.height, W = camera.width).
    ``sh_degree`` is clipped to what the snapshot's coefficients hold; a dynamic scene's
    Gaussians are deformed to ``time`` once its warm-up is over."""
    degree = max(0, min(int(sh_degree), available_sh_degree(snapshot.params)))
    params = snapshot.params
    if snapshot.field is not None:
        with torch.no_grad():
            params = params_at_time(params, snapshot.field, time)
    image, alpha, depth = render_camera(params, camera, degree, background, settings)
    if output == "rgb":
        return to_uint8(image)
    if output == "alpha":
        return to_uint8(np.repeat(alpha[..., None], 3, axis=2))
    if output == "depth":
        near, far = depth_range([depth], [alpha])
        return colorize_depth(depth, alpha, near, far)
    raise ValueError(f"unknown viewer output {output!r}; choose rgb, depth or alpha")
