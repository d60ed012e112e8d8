"""Pick the parser for a ``--data`` argument and normalise the result.

``builtin:NAME`` -> generated (or cached) built-in scene, read as COLMAP (static scenes) or
Neu3D (dynamic ones); a folder with ``sparse/`` -> COLMAP; a folder with ``poses_bounds.npy``
-> Neu3D / DyNeRF; a ``transforms.json`` file, or a folder holding one -> transforms.json.
"""

from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

from .builtin import ensure_builtin
from .colmap import read_colmap
from .errors import DataError
from .images import conversion_note
from .neu3d import is_neu3d, read_neu3d
from .parsed import ParsedScene, ParseOptions, normalize_scene
from .transforms_json import BLENDER_LAYOUT, read_transforms

BUILTIN_PREFIX = "builtin:"


def resolve_data(data: str, cache_dir: Path) -> tuple[str, Path]:
    """(format, path) for a data argument; format is "colmap", "neu3d" or "transforms".

    Built-in scenes are generated into (or reused from) ``cache_dir/scenes``."""
    if data.startswith(BUILTIN_PREFIX):
        name = data[len(BUILTIN_PREFIX):]
        path = ensure_builtin(name, Path(cache_dir).expanduser() / "scenes")
        return ("neu3d" if is_neu3d(path) else "colmap"), path
    path = Path(data).expanduser()
    if not path.exists():
        raise DataError(f"--data {data}", "path does not exist (and is not builtin:NAME)")
    if path.is_file():
        if path.suffix.lower() == ".json":
            return "transforms", path
        raise DataError(path, "a data file must be a transforms.json; otherwise pass the dataset folder")
    if (path / "sparse").is_dir():
        return "colmap", path
    if is_neu3d(path):
        return "neu3d", path
    if (path / "transforms.json").is_file():
        return "transforms", path / "transforms.json"
    if (path / "transforms_train.json").is_file():
        return "transforms", path  # Blender / NeRF-synthetic: transforms_{train,val,test}.json
    raise DataError(path, "not a dataset: expected sparse/0 (COLMAP), transforms.json, transforms_train.json "
                    "or poses_bounds.npy (Neu3D)")


def parse_dataset(data: str, options: ParseOptions, normalize: bool = True) -> ParsedScene:
    """Parse ``data`` and return it normalised (see :mod:`exploregs_plugin.data.parsed`)."""
    kind, path = resolve_data(data, options.cache_root)
    readers = {"colmap": read_colmap, "neu3d": read_neu3d, "transforms": read_transforms}
    scene = readers[kind](path, options)
    if data.startswith(BUILTIN_PREFIX):
        scene = replace(scene, name=data[len(BUILTIN_PREFIX):])
    # grayscale and transparent images are converted on purpose, and one line says so (a Blender
    # folder's RGBA images are its convention: the datamanager reports on its background)
    note = conversion_note({im.name: im.pixel_kind for im in scene.images},
                           skip=("alpha",) if scene.layout == BLENDER_LAYOUT else ())
    if note is not None:
        print(f"note: {scene.root}: {note}", file=sys.stderr, flush=True)
    return normalize_scene(scene, enabled=normalize)
