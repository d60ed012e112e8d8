"""Live viser viewer: training cameras, initial points and the current Gaussians rendered by
the CPU rasterizer from the browser's camera (``eg-train ... --viewer``, ``eg-view``).

``ViewerConfig`` is importable without loading viser (the trainer's config holds one); the
server side (``Viewer``, ``ViewerScene``) is imported on first use.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from exploregs_plugin.runtime.lazy_names import lazy_names
from exploregs_plugin.viewer.config import ViewerConfig

if TYPE_CHECKING:
    from exploregs_plugin.viewer.scene import ViewerScene
    from exploregs_plugin.viewer.viewer import Viewer

__all__ = ["Viewer", "ViewerConfig", "ViewerScene"]
__getattr__ = lazy_names(__name__, {"Viewer": ".viewer", "ViewerScene": ".scene"})
