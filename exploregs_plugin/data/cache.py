"""Where ExploreGS keeps generated scenes and derived images: ``$EXPLOREGS_CACHE`` or
``~/.cache/exploregs`` (built-in scenes go to its ``scenes/`` folder)."""

from __future__ import annotations

import os
from pathlib import Path

CACHE_ENV = "EXPLOREGS_CACHE"
DEFAULT_CACHE = Path("~/.cache/exploregs")


def cache_root() -> Path:
    """``$EXPLOREGS_CACHE`` when set and not empty, else ``~/.cache/exploregs`` (expanded)."""
    return Path(os.environ.get(CACHE_ENV) or DEFAULT_CACHE).expanduser()
