"""What the live viewer shows and how (``eg-train ... --viewer`` and ``eg-view``): the settings
``Viewer`` reads. ``ViewerConfig`` (``viewer/config.py``) adds ``setup()``, which builds the viewer;
the two are apart so that the viewer imports its settings and the config imports the viewer, with
no import circle between them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

from exploregs_plugin.io.config_files import unset
from exploregs_plugin.viewer.outputs import OUTPUT_KINDS, OutputKind


@dataclass
class ViewerSettings:
    """The viser server, what it shows, and how much CPU its renders may take."""

    host: str = "127.0.0.1"
    """Address the web server binds to (0.0.0.0 to reach it from other machines)."""
    port: int = 8080
    """Port of the web server; when taken, the next free one is used (0 = any free port)."""
    moving_resolution: int = 192
    """Longest image side in pixels of the renders made while the browser's camera moves."""
    rest_resolution: int = 640
    """Longest image side in pixels once the camera has stopped (for rest_delay seconds)."""
    rest_delay: float = 0.25
    """Seconds without camera motion after which the sharp (rest_resolution) render is made."""
    max_render_share: float = 0.2
    """Largest share of CPU time the renders take while training runs (after a t-second render
    the thread sleeps t (1 - share) / share; 1 = no limit, as in eg-view and a paused run)."""
    output: OutputKind = "rgb"
    """What the render shows: rgb, depth (expected depth, coloured) or alpha (accumulated opacity)."""
    sh_degree: Annotated[int | None, unset("the model's largest")] = None
    """Spherical-harmonics degree of the viewer's renders."""
    jpeg_quality: int = 85
    """JPEG quality of the frames sent to the browser (1-100)."""
    max_thumbnails: int = 64
    """Training cameras drawn with their image as a thumbnail (evenly spread; the others as frustums)."""
    thumbnail_height: int = 64
    """Height in pixels of the frustum thumbnails."""
    frustum_scale: Annotated[float | None, unset("3% of the scene extent")] = None
    """Length of the drawn camera frustums in world units."""
    max_points: int = 100_000
    """Largest number of initial points shown (evenly subsampled beyond it)."""
    point_size: Annotated[float | None, unset("0.3% of the scene extent")] = None
    """Size of the shown initial points in world units."""
    show_points: bool = False
    """Show the initial points at start (they cover the splats; a checkbox toggles them)."""
    serve_after_training: bool = False
    """Keep serving the finished scene after training ends, until Ctrl-C."""

    def __post_init__(self) -> None:
        if not 0 <= self.port <= 65535:
            raise ValueError(f"viewer port must be in 0..65535, got {self.port}")
        if self.moving_resolution < 16 or self.rest_resolution < 16:
            raise ValueError(
                "viewer moving_resolution and rest_resolution must be >= 16 pixels, got "
                f"{self.moving_resolution} and {self.rest_resolution}"
            )
        if not 0.0 < self.max_render_share <= 1.0:
            raise ValueError(f"viewer max_render_share must be in (0, 1], got {self.max_render_share}")
        if self.rest_delay < 0.0:
            raise ValueError(f"viewer rest_delay must be >= 0 seconds, got {self.rest_delay}")
        if self.output not in OUTPUT_KINDS:
            raise ValueError(f"viewer output must be one of {', '.join(OUTPUT_KINDS)}, got {self.output!r}")
        if self.sh_degree is not None and not 0 <= self.sh_degree <= 3:
            raise ValueError(f"viewer sh_degree must be in 0..3, got {self.sh_degree}")
        if not 1 <= self.jpeg_quality <= 100:
            raise ValueError(f"viewer jpeg_quality must be in 1..100, got {self.jpeg_quality}")
        if self.max_thumbnails < 0 or self.thumbnail_height < 8:
            raise ValueError("viewer max_thumbnails must be >= 0 and thumbnail_height >= 8")
        if self.max_points < 0:
            raise ValueError(f"viewer max_points must be >= 0, got {self.max_points}")
        for name in ("frustum_scale", "point_size"):
            value = getattr(self, name)
            if value is not None and not value > 0.0:
                raise ValueError(f"viewer {name} must be > 0 when set, got {value}")
