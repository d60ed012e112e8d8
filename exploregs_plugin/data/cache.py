"""Where ExploreGS keeps generated scenes and derived images: ``$EXPLOREGS_CACHE``, else the
platform cache folder ``$XDG_CACHE_HOME/exploregs`` (``~/.cache/exploregs`` when unset).

Built-in scenes go to its ``scenes/`` folder, images derived from a dataset (resized,
undistorted, decoded video frames) to ``derived/<dataset name>-<hash of its absolute path>/``;
a dataset folder is never written to unless asked (``--datamanager.cache-beside-data``).
"""

from __future__ import annotations

import os
from pathlib import Path

CACHE_ENV = "EXPLOREGS_CACHE"
DEFAULT_CACHE = Path("~/.cache/exploregs")


def cache_root() -> Path:
    """``$EXPLOREGS_CACHE`` when set and not empty, else ``$XDG_CACHE_HOME/exploregs``, else
    ``~/.cache/exploregs`` (expanded)."""
    if os.environ.get(CACHE_ENV):
        return Path(os.environ[CACHE_ENV]).expanduser()
    xdg = os.environ.get("XDG_CACHE_HOME")
    # the XDG spec ignores a relative path
    if xdg and Path(xdg).expanduser().is_absolute():
        return Path(xdg).expanduser() / "exploregs"
    return DEFAULT_CACHE.expanduser()
