"""What a capture is: a folder of photos, one video, several videos or a folder of videos.

``find_capture`` classifies the input of ``eg-process`` (and of ``--data`` without poses) and
lists its files in name order; ``input_key`` is what the output folder remembers of it, so a rerun
on the same input resumes and another input is refused.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from ..errors import DataError

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".heic", ".heif", ".tif", ".tiff", ".bmp", ".webp")
VIDEO_SUFFIXES = (".mp4", ".mov", ".m4v", ".avi", ".mkv", ".webm")
MIN_IMAGES = 3
"""Two views pose only up to their baseline's length; three are the fewest that tie a scale."""


@dataclass(frozen=True)
class Capture:
    """The files of one input: ``kind`` "images" (photos) or "videos"; ``where`` names it in
    messages (the folder given, or the first video file given)."""

    kind: Literal["images", "videos"]
    files: tuple[Path, ...]
    where: Path


def is_image(path: Path) -> bool:
    return path.is_file() and path.suffix.lower() in IMAGE_SUFFIXES and not path.name.startswith(".")


def is_video(path: Path) -> bool:
    return path.is_file() and path.suffix.lower() in VIDEO_SUFFIXES and not path.name.startswith(".")


def photo_folder(folder: Path) -> Path:
    """The folder that holds the photos: ``folder/images`` for a dataset folder, else ``folder``."""
    return folder / "images" if (folder / "images").is_dir() else folder


def is_capture(path: Path) -> bool:
    """True for a video file, or a folder of photos or videos that has no poses (no ``sparse/``)."""
    if path.is_file():
        return is_video(path)
    if not path.is_dir() or (path / "sparse").is_dir():
        return False
    return any(is_image(p) or is_video(p) for p in photo_folder(path).iterdir())


def find_capture(inputs: list[Path]) -> Capture:
    """Classify ``inputs`` (one folder or video, or several videos); bad input is one DataError."""
    if not inputs:
        raise DataError("INPUT", "give a folder of photos, a video file, several video files or a folder of videos")
    for path in inputs:
        if not path.exists():
            raise DataError(path, "does not exist")
    if len(inputs) > 1:
        for path in inputs:
            if not is_video(path):
                raise DataError(path, f"several inputs must all be videos ({', '.join(VIDEO_SUFFIXES)})")
        return Capture("videos", tuple(inputs), inputs[0])
    path = inputs[0]
    if path.is_file():
        if not is_video(path):
            raise DataError(path, f"not a video ({', '.join(VIDEO_SUFFIXES)}): pass a folder of photos or a video")
        return Capture("videos", (path,), path)
    folder = photo_folder(path)
    entries = sorted(folder.iterdir())
    images = tuple(p for p in entries if is_image(p))
    videos = tuple(p for p in entries if is_video(p))
    if images and videos:
        raise DataError(folder, f"holds both photos ({images[0].name}) and videos ({videos[0].name}): "
                        "pass one kind (several videos may be given as separate arguments)")
    if videos:
        return Capture("videos", videos, folder)
    if len(images) < MIN_IMAGES:
        raise DataError(folder, f"holds {len(images)} image(s) ({', '.join(IMAGE_SUFFIXES)}); posing needs at "
                        f"least {MIN_IMAGES} overlapping photos")
    return Capture("images", images, folder)


def input_key(capture: Capture) -> list[list]:
    """[absolute path, size, modification time] of every input file: what a rerun must match."""
    rows = []
    for path in capture.files:
        info = path.stat()
        rows.append([str(path.resolve()), info.st_size, info.st_mtime_ns])
    return rows
