"""eg-scenes: write a built-in ground-truth scene anywhere, or list the presets.

    eg-scenes list
    eg-scenes make default --out scenes/default
    eg-scenes make farside --out /tmp/fs --width 320 --height 240 --views 48 --seed 3
"""

from __future__ import annotations

import json
import sys
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Annotated, Union

import tyro

from exploregs_plugin.data.builtin import PRESETS, make_scene, preset_by_name
from exploregs_plugin.data.errors import DataError


@dataclass
class Make:
    """Generate a built-in scene (a COLMAP dataset with depths, region masks and a split)."""

    name: Annotated[str, tyro.conf.Positional, tyro.conf.arg(metavar="NAME")]
    """Preset to start from (see `eg-scenes list`)."""
    out: Path
    """Output folder (created; must be empty unless --overwrite)."""
    width: int | None = None
    """Image width in pixels (default: the preset's)."""
    height: int | None = None
    """Image height in pixels (default: the preset's)."""
    views: int | None = None
    """Number of views (default: the preset's)."""
    seed: int | None = None
    """Seed of the layout jitter, cameras and sparse points (default: the preset's)."""
    points: int | None = None
    """Number of SfM-like sparse points (default: the preset's)."""
    overwrite: bool = False
    """Replace an existing non-empty output folder."""


@dataclass
class List:
    """Print the presets and their settings."""


Command = Union[
    Annotated[Make, tyro.conf.subcommand("make")],
    Annotated[List, tyro.conf.subcommand("list")],
]


def main(argv: list[str]) -> int:
    command = tyro.cli(Command, args=argv, description="Built-in ExploreGS scenes with ground truth.")
    if isinstance(command, List):
        for name, preset in PRESETS.items():
            print(f"{name:16s} {json.dumps(asdict(preset))}")
        return 0
    try:
        preset = preset_by_name(command.name)
        changes = {
            "width": command.width, "height": command.height, "n_views": command.views,
            "seed": command.seed, "n_points": command.points,
        }
        preset = replace(preset, **{k: v for k, v in changes.items() if v is not None})
        start = time.perf_counter()
        out = make_scene(preset, command.out, overwrite=command.overwrite)
    except DataError as err:
        print(f"eg-scenes: error: {err}", file=sys.stderr)
        return 2
    seconds = time.perf_counter() - start
    print(f"wrote {command.name} ({preset.width}x{preset.height}, {preset.n_views} views, seed "
          f"{preset.seed}) to {out} in {seconds:.1f} s")
    return 0


def entrypoint() -> None:
    raise SystemExit(main(sys.argv[1:]))


if __name__ == "__main__":
    entrypoint()
