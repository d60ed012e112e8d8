"""Pick the parser for a ``--data`` argument and normalise the result.

``builtin:NAME`` -> generated (or cached) built-in scene, read as COLMAP (static scenes) or
Neu3D (dynamic ones); a folder with ``sparse/`` -> COLMAP; a folder with ``poses_bounds.npy``
-> Neu3D / DyNeRF; a ``transforms.json`` file, or a folder holding one -> transforms.json; a
capture without poses (a folder of photos, a dataset folder with ``images/`` but no ``sparse/``,
a video file, a folder of videos) -> posed by :mod:`exploregs_plugin.data.process` into the cache
once, then read as COLMAP.
"""

from __future__ import annotations

import shlex
import sys
from dataclasses import replace
from pathlib import Path

import yaml

from exploregs_plugin.io.checkpoint import CHECKPOINT_DIR, RUN_CONFIG
from exploregs_plugin.io.config_files import read_yaml

from .builtin.presets import ensure_builtin
from .colmap import read_colmap
from .errors import DataError
from .images import conversion_note, derived_cache_dir
from .neu3d import CAMERA_NAME, POSES_FILE, is_neu3d, read_neu3d
from .process import is_capture, is_posed, process_capture
from .parsed import ParsedScene, ParseOptions, normalize_scene
from .transforms_json import BLENDER_LAYOUT, read_transforms

BUILTIN_PREFIX = "builtin:"


def another_commands_input(path: Path) -> str | None:
    """Why ``path`` is not a dataset when it is another input of the commands: a PLY of trained
    Gaussians, or an eg-train run folder (or a checkpoint in one), named with the dataset it
    trained on, so that the one line says what the path is."""
    if path.is_file() and path.suffix.lower() == ".ply":
        return "a PLY of trained Gaussians, not a dataset"
    run = path.parent.parent if path.is_file() and path.parent.name == CHECKPOINT_DIR else path
    if not (run / RUN_CONFIG).is_file():
        return None
    try:
        data = read_yaml((run / RUN_CONFIG).read_text())["pipeline"]["datamanager"]["data"]
    except (OSError, yaml.YAMLError, KeyError, TypeError):
        data = f"the dataset named in {run / RUN_CONFIG}"
    return (f"an eg-train run, not a dataset: it trained on {data} "
            f"(eg-train --resume {shlex.quote(str(run))} continues it)")


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
    other = another_commands_input(path)
    if other is not None:
        raise DataError(path, other)
    if path.is_file():
        if path.suffix.lower() == ".json":
            return "transforms", path
        if is_capture(path):  # a video
            return "colmap", posed_capture(path, Path(cache_dir).expanduser())
        raise DataError(path, "a data file must be a transforms.json; otherwise pass the dataset folder")
    if (path / "sparse").is_dir():
        return "colmap", path
    if is_neu3d(path):
        return "neu3d", path
    if (path / "transforms.json").is_file():
        return "transforms", path / "transforms.json"
    if (path / "transforms_train.json").is_file():
        return "transforms", path  # Blender / NeRF-synthetic: transforms_{train,val,test}.json
    cameras = sorted(p.name for p in path.iterdir() if p.is_dir() and CAMERA_NAME.match(p.name))
    if cameras:  # a multi-view video's camera folders: their frames are moments, not one still scene
        raise DataError(path, f"not a dataset: it holds camera folders ({', '.join(cameras[:3])}"
                        f"{', ...' if len(cameras) > 3 else ''}) of a multi-view video but no {POSES_FILE} (Neu3D)")
    if is_capture(path):  # photos or videos without poses
        return "colmap", posed_capture(path, Path(cache_dir).expanduser())
    raise DataError(path, "not a dataset: expected sparse/0 (COLMAP), transforms.json, transforms_train.json, "
                    "poses_bounds.npy (Neu3D), or photos or videos to pose")


def posed_capture(path: Path, cache_dir: Path) -> Path:
    """The COLMAP dataset posed from the capture ``path`` in the cache (``derived/``, beside the
    derived images; never in the user's folder): made on first use, reused after."""
    out = derived_cache_dir(path, "posed", cache_dir)
    reused = is_posed([path], out)
    if reused:
        print(f"note: {path} has no camera poses: using those posed earlier in {out}", file=sys.stderr, flush=True)
    else:
        print(f"note: {path} has no camera poses: posing it (as eg-process does) into {out}; the next run "
              "reuses it", file=sys.stderr, flush=True)
    process_capture([path], out, replace_other=True, summary=not reused)  # a changed capture is posed again
    return out


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
