"""eg-scenes: write a built-in ground-truth scene anywhere, list the presets, describe a scene.

    eg-scenes list
    eg-scenes stats scenes/default               # what docs/data.md tabulates
    eg-scenes make default --out scenes/default
    eg-scenes make farside --out /tmp/fs --width 320 --height 240 --views 48 --seed 3
    eg-scenes make dynamic --out /tmp/dyn --cameras 8 --frames 60     # a dynamic scene (Neu3D layout)
"""

from __future__ import annotations

import json
import sys
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Annotated, Union

import numpy as np
import tyro
from PIL import Image

from exploregs_plugin.data.builtin.presets import PRESETS, make_scene, preset_by_name
from exploregs_plugin.data.builtin.dynamic import DYNAMIC_PRESETS, DynamicPreset
from exploregs_plugin.data.colmap import read_colmap
from exploregs_plugin.data.neu3d import is_neu3d, read_neu3d
from exploregs_plugin.data.errors import DataError
from exploregs_plugin.data.parsed import REGION_LABELS, ParseOptions
from exploregs_plugin.scripts import parse_cli
from exploregs_plugin.runtime.threads import apply_threads


@dataclass
class Make:
    """Generate a built-in scene: a COLMAP dataset with depths, region masks and a split, or for a
    dynamic preset a Neu3D multi-view clip with the same ground truth."""

    name: Annotated[str, tyro.conf.Positional, tyro.conf.arg(metavar="NAME")]
    """Preset to start from (see `eg-scenes list`)."""
    out: Path
    """Output folder (created; must be empty unless --overwrite)."""
    width: int | None = None
    """Image width in pixels (default: the preset's)."""
    height: int | None = None
    """Image height in pixels (default: the preset's)."""
    views: int | None = None
    """Number of views of a static scene (default: the preset's)."""
    cameras: int | None = None
    """Number of cameras of a dynamic scene (default: the preset's)."""
    frames: int | None = None
    """Number of frames of a dynamic scene's clip (default: the preset's)."""
    seed: int | None = None
    """Seed of the layout jitter, cameras and sparse points (default: the preset's)."""
    points: int | None = None
    """Number of SfM-like sparse points (default: the preset's)."""
    overwrite: bool = False
    """Replace an existing non-empty output folder."""


@dataclass
class List:
    """Print the presets and their settings as a table."""

    json: bool = False
    """Print one JSON object (preset name -> settings) instead of the table."""


@dataclass
class Stats:
    """Print a generated scene's split, sparse points and test-view region fractions."""

    folder: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="DIR")]
    """A folder written by `eg-scenes make` (or a cached builtin scene)."""


Command = Union[
    Annotated[Make, tyro.conf.subcommand("make")],
    Annotated[List, tyro.conf.subcommand("list")],
    Annotated[Stats, tyro.conf.subcommand("stats")],
]


def scene_stats(folder: Path) -> dict[str, float | int]:
    """Split sizes, point count, share of points beyond the far radius, region shares over the
    test views, size on disk (MB)."""
    meta = json.loads((folder / "scene.json").read_text())
    scene = read_neu3d(folder, ParseOptions()) if is_neu3d(folder) else read_colmap(folder, ParseOptions())
    test = set(scene.split["test"]) if scene.split else set()
    labels = [np.asarray(Image.open(im.mask_path)) for im in scene.images
              if im.name in test and im.mask_path is not None]
    labels_all = np.stack(labels) if labels else np.zeros((0,), dtype=np.uint8)
    points = scene.points if scene.points is not None else np.zeros((0, 3))
    far_points = np.linalg.norm(points, axis=1) > meta["preset"]["far_radius"]
    stats: dict[str, float | int] = {
        "train_views": len(scene.images) - len(test),
        "test_views": len(test),
        "points": len(points),
        "far_points_share": float(far_points.mean()) if len(points) else 0.0,
    }
    for region, value in REGION_LABELS.items():
        stats[f"test_{region}_share"] = float((labels_all == value).mean()) if labels_all.size else 0.0
    stats["megabytes"] = sum(f.stat().st_size for f in folder.rglob("*") if f.is_file()) / 1e6
    stats["generation_seconds"] = meta["seconds"]
    return stats


def preset_table(settings: dict[str, dict]) -> str:
    """One row per preset, one column per setting, aligned for a terminal."""
    columns = ["name", *next(iter(settings.values()))]
    rows = [[name, *(f"{v:g}" if isinstance(v, float) else str(v) for v in values.values())]
            for name, values in settings.items()]
    widths = [max(len(str(c)), *(len(r[i]) for r in rows)) for i, c in enumerate(columns)]
    lines = ["  ".join(c.ljust(w) for c, w in zip(columns, widths)).rstrip()]
    lines += ["  ".join(v.ljust(w) for v, w in zip(r, widths)).rstrip() for r in rows]
    return "\n".join(lines)


def main(argv: list[str]) -> int:
    command = parse_cli("eg-scenes", Command, "Built-in ExploreGS scenes with ground truth.", argv)
    if isinstance(command, List):
        settings = {name: asdict(preset) for name, preset in PRESETS.items()}
        dynamic = {name: asdict(preset) for name, preset in DYNAMIC_PRESETS.items()}
        if command.json:
            print(json.dumps({**settings, **dynamic}, indent=1))
        else:
            print(preset_table(settings) + "\n\ndynamic scenes:\n" + preset_table(dynamic))
        return 0
    if isinstance(command, Stats):
        if not (command.folder / "scene.json").is_file():
            why = ("no such folder" if not command.folder.exists() else
                   "not a scene written by eg-scenes make (it has no scene.json)")
            print(f"eg-scenes: error: {command.folder}: {why}", file=sys.stderr)
            return 2
        try:
            stats = scene_stats(command.folder)
        except (DataError, OSError, KeyError, ValueError) as err:
            print(f"eg-scenes: error: {command.folder}: not a generated scene ({err})", file=sys.stderr)
            return 2
        print(json.dumps(stats, indent=1))
        return 0
    try:
        preset = preset_by_name(command.name)
        dynamic = isinstance(preset, DynamicPreset)
        if dynamic and command.views is not None:
            raise DataError("--views", f"{command.name} is a dynamic scene: set --cameras and --frames")
        if not dynamic and (command.cameras is not None or command.frames is not None):
            raise DataError("--cameras/--frames", f"{command.name} is a static scene: set --views")
        changes = {"width": command.width, "height": command.height, "seed": command.seed, "n_points": command.points}
        if dynamic:
            changes.update(n_cameras=command.cameras, n_frames=command.frames)
        else:
            changes["n_views"] = command.views
        preset = replace(preset, **{k: v for k, v in changes.items() if v is not None})
        start = time.perf_counter()
        out = make_scene(preset, command.out, overwrite=command.overwrite)
    except DataError as err:
        print(f"eg-scenes: error: {err}", file=sys.stderr)
        return 2
    seconds = time.perf_counter() - start
    views = (f"{preset.n_cameras} cameras x {preset.n_frames} frames" if isinstance(preset, DynamicPreset)
             else f"{preset.n_views} views")
    print(f"wrote {command.name} ({preset.width}x{preset.height}, {views}, seed {preset.seed}) to {out} "
          f"in {seconds:.1f} s")
    return 0


def entrypoint() -> None:
    apply_threads()  # one thread per CPU this process may use, as in every command
    raise SystemExit(main(sys.argv[1:]))


if __name__ == "__main__":
    entrypoint()
