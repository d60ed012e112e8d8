"""Datasets: COLMAP and transforms.json parsers, built-in ground-truth scenes, the DataManager.

Public entry points::

    from exploregs_plugin.data import DataManagerConfig
    dm = DataManagerConfig(data="builtin:tiny").setup()
"""

from .cache import CACHE_ENV, cache_root
from .datamanager import DataManager, DataManagerConfig
from .errors import DataError
from .parsed import REGION_LABELS, ImageRecord, Normalization, ParsedScene, ParseOptions
from ..runtime.lazy_names import lazy_names

# The readers and the built-in scenes load on first use: they import pycolmap, PIL and the scene
# generators, which a command's --help or a config never needs (docs/training.md, "Startup").
_LAZY = {
    "PRESETS": ".builtin.presets", "ScenePreset": ".builtin.presets", "ensure_builtin": ".builtin.presets",
    "make_scene": ".builtin.presets", "read_colmap": ".colmap", "parse_dataset": ".dataparser",
    "read_transforms": ".transforms_json", "write_transforms": ".transforms_json",
}

__getattr__ = lazy_names(__name__, _LAZY)

__all__ = [
    "CACHE_ENV",
    "DataError",
    "DataManager",
    "DataManagerConfig",
    "ImageRecord",
    "Normalization",
    "PRESETS",
    "ParseOptions",
    "ParsedScene",
    "REGION_LABELS",
    "ScenePreset",
    "cache_root",
    "ensure_builtin",
    "make_scene",
    "parse_dataset",
    "read_colmap",
    "read_transforms",
    "write_transforms",
]
