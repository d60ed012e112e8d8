"""Datasets: COLMAP and transforms.json parsers, built-in ground-truth scenes, the DataManager.

Public entry points::

    from exploregs_plugin.data import DataManagerConfig
    dm = DataManagerConfig(data="builtin:tiny").setup()
"""

from .builtin.presets import PRESETS, ScenePreset, ensure_builtin, make_scene
from .cache import CACHE_ENV, cache_root
from .colmap import read_colmap
from .datamanager import DataManager, DataManagerConfig
from .dataparser import parse_dataset
from .errors import DataError
from .parsed import REGION_LABELS, ImageRecord, Normalization, ParsedScene, ParseOptions
from .transforms_json import read_transforms, write_transforms

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
