"""eg-process: photos or videos in, a COLMAP dataset (images/ + sparse/0) out, posed with pycolmap.

    eg-process path/to/photos --out path/to/dataset          # a folder of photos (JPEG, PNG, HEIC)
    eg-process path/to/DCIM --out path/to/dataset            # photos in subfolders (100APPLE/, ...)
    eg-process clip.mp4 --out path/to/dataset                # a video (its sharpest 150 frames)
    eg-process a.mp4 b.mp4 --out path/to/dataset             # several videos (one camera each)
    eg-process path/to/photos --out path/to/dataset --mapper global
    eg-train exploregs-seedsplit --data path/to/dataset      # then train on it

A rerun with the same --out resumes: finished stages are skipped. The dataset folder also holds
database.db, process_report.json and process_top_view.png.
"""

from __future__ import annotations

import shlex
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated

import tyro

from exploregs_plugin.data.process import ProcessConfig
from exploregs_plugin.scripts import parse_cli, run_cli


@dataclass
class ProcessArgs:
    """Pose a capture (a folder of photos, a video, several videos or a folder of videos) into a
    COLMAP dataset that every other command reads."""

    inputs: Annotated[list[Path], tyro.conf.Positional,
                      tyro.conf.arg(metavar="INPUT", help_behavior_hint="(required)")]
    """A folder of photos (or of subfolders of photos, as a phone exports them; or a dataset folder
    whose images/ has no sparse/), a video file, several video files or a folder of videos. Never
    written to."""
    out: Path
    """The dataset folder to write (new or empty, or an earlier eg-process output to resume)."""
    options: Annotated[ProcessConfig, tyro.conf.OmitArgPrefixes] = field(default_factory=ProcessConfig)


def main(args: ProcessArgs) -> int:
    from exploregs_plugin.data.process import process_capture  # pycolmap loads here, not for --help

    process_capture(args.inputs, args.out, args.options)
    # quoted, so that the command pastes as it is when the path holds a space
    print(f"dataset: {args.out} (train with: eg-train exploregs-seedsplit --data {shlex.quote(str(args.out))})",
          flush=True)
    return 0


def parse_args(argv: list[str] | None = None) -> ProcessArgs:
    """The command line as ProcessArgs; a wrong one (an unknown flag, a bad value) is one line."""
    return parse_cli("eg-process", ProcessArgs, "Pose photos or videos into a COLMAP dataset (images/ + sparse/0) "
                     "with pycolmap.", argv)


def entrypoint() -> None:
    raise SystemExit(run_cli("eg-process", main, parse_args(sys.argv[1:])))


if __name__ == "__main__":
    entrypoint()
