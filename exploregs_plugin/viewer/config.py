"""Settings of the live viewer (``eg-train ... --viewer`` and ``eg-view``) and the one way to start
it (``ViewerConfig.setup``)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from exploregs_plugin.viewer.settings import ViewerSettings

if TYPE_CHECKING:
    from exploregs_plugin.viewer.viewer import Viewer


@dataclass
class ViewerConfig(ViewerSettings):
    """The viser server, what it shows, and how much CPU its renders may take (the fields:
    ``ViewerSettings``); ``setup()`` starts it."""

    def setup(self, source: Any, *, training: bool = True, step: int = 0) -> "Viewer":
        """Start the viewer on ``source``: a ``Pipeline`` (training or a loaded run; ``step`` =
        steps it has done) or a ``ViewerScene``. ``training=False`` serves a fixed scene (no
        pause control, no CPU throttling)."""
        from exploregs_plugin.viewer.scene import ViewerScene
        from exploregs_plugin.viewer.viewer import Viewer

        scene = source if isinstance(source, ViewerScene) else ViewerScene.from_pipeline(source, step=step)
        return Viewer(self, scene, training=training)
