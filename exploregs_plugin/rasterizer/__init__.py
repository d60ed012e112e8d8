"""Gaussian rasterizer (3DGS image model): the pure-torch reference, with separable position
paths, on any device; a compiled CPU compositor and gsplat's CUDA kernels as further backends
(``RasterSettings.backend``: auto, torch, cpp, gsplat; see ``backends.py``).

``rasterize(means, quats, scales, opacities, sh_coeffs, camera, ...)`` (``camera``: an
``exploregs_plugin.cameras.Camera``, its viewmat, K, size and depth range)
returns ``image [H, W, 3], alpha [H, W, 1], depth [H, W, 1], info`` where info holds
"means2d" [N, 2] (non-leaf; call ``retain_grad()`` for the screen-space gradient), "radii"
[N, 2] int32 (0 = culled), "visible" [N] bool, "depths" [N], "conics" [N, 3],
"camera_center" [3], "width", "height", "n_cameras" (= 1) and "n_pairs".
``trace_pixel`` lists the Gaussians composited at one pixel with their alpha, transmittance
and dC/dalpha.
"""

from .backends import backend_line, backend_problem, resolve_backend
from .gsplat_backend import BackendError
from .rasterize import rasterize, rasterize_branched
from .settings import RasterSettings
from .trace import trace_pixel

__all__ = ["rasterize", "rasterize_branched", "trace_pixel", "RasterSettings", "BackendError", "backend_problem", "backend_line",
           "resolve_backend"]
