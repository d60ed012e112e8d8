"""What a capture is: a folder of photos, one video, several videos or a folder of videos.

``find_capture`` classifies the input of ``eg-process`` (and of ``--data`` without poses) and
lists its files in name order; ``input_key`` is what the output folder remembers of it, so a rerun
on the same input resumes and another input is refused.

Phones and cameras export photos into subfolders (``DCIM/100APPLE/IMG_0001.HEIC``): a folder with
no photo or video of its own takes the photos of its subfolders, and ``recursive`` takes them
beside the folder's own. Their names keep the path below the folder (``100APPLE/IMG_0001.jpg``
under ``images/``), unique and stable as the names of several videos' frames are.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Literal

from ...io.checkpoint import RUN_CONFIG
from ..errors import DataError

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".heic", ".heif", ".tif", ".tiff", ".bmp", ".webp")
VIDEO_SUFFIXES = (".mp4", ".mov", ".m4v", ".avi", ".mkv", ".webm")
MIN_IMAGES = 3
"""Two views pose only up to their baseline's length; three are the fewest that tie a scale."""
STATE_NAME = "process_state.json"
"""eg-process's record in its output folder (``run.py``)."""
OTHER_INPUT_MARKS = ("sparse", STATE_NAME, "transforms.json", "transforms_train.json", "poses_bounds.npy",
                     RUN_CONFIG)
"""A subfolder holding one of these is a dataset, an eg-process output or an eg-train run, not
photos of this capture: its images (or renders) are passed over, so that a folder of datasets or
runs is not posed as one capture."""


@dataclass(frozen=True)
class Capture:
    """The files of one input: ``kind`` "images" (photos) or "videos"; ``where`` names it in
    messages (the folder given, or the first video file given), and photos are named by their
    path below it; ``note``: one line on the subfolders' photos taken or left out ("": none)."""

    kind: Literal["images", "videos"]
    files: tuple[Path, ...]
    where: Path
    note: str = ""


def is_image(path: Path) -> bool:
    return path.is_file() and path.suffix.lower() in IMAGE_SUFFIXES and not path.name.startswith(".")


def is_video(path: Path) -> bool:
    return path.is_file() and path.suffix.lower() in VIDEO_SUFFIXES and not path.name.startswith(".")


def photo_folder(folder: Path) -> Path:
    """The folder that holds the photos: ``folder/images`` for a dataset folder, else ``folder``."""
    return folder / "images" if (folder / "images").is_dir() else folder


def relative_name(path: Path, folder: Path) -> str:
    """``path`` below ``folder`` with ``/`` between parts: the image's name in the dataset."""
    return path.relative_to(folder).as_posix()


def files_below(folder: Path) -> Iterator[Path]:
    """The photos and videos in the subfolders of ``folder``, at any depth (not its own files).
    Hidden folders (``.thumbnails``) and folders of another input (OTHER_INPUT_MARKS) are passed
    over; a linked folder is not followed, so a link to a parent cannot loop."""
    for root, dirs, files in os.walk(folder):
        here = Path(root)
        if here != folder and any((here / mark).exists() for mark in OTHER_INPUT_MARKS):
            dirs[:] = []
            continue
        dirs[:] = sorted(d for d in dirs if not d.startswith("."))
        if here == folder:
            continue
        for name in sorted(files):
            path = here / name
            if is_image(path) or is_video(path):
                yield path


def is_capture(path: Path) -> bool:
    """True for a video file, or a folder of photos or videos, or of subfolders holding them,
    that has no poses (no ``sparse/``)."""
    if path.is_file():
        return is_video(path)
    if not path.is_dir() or (path / "sparse").is_dir():
        return False
    folder = photo_folder(path)
    return (any(is_image(p) or is_video(p) for p in folder.iterdir())
            or next(files_below(folder), None) is not None)


def _count(n: int, noun: str) -> str:
    return f"{n} {noun}{'' if n == 1 else 's'}"


def _subfolders(folder: Path, photos: list[Path], most: int = 3) -> tuple[str, int]:
    """('its 3 subfolders (100APPLE, 101APPLE, 102APPLE)', 3): the subfolders holding ``photos``."""
    parents = sorted({p.parent.relative_to(folder).as_posix() for p in photos})
    shown = ", ".join(parents[:most]) + (f" and {len(parents) - most} more" if len(parents) > most else "")
    return f"its {_count(len(parents), 'subfolder')} ({shown})", len(parents)


def _folder_capture(folder: Path, recursive: bool) -> Capture:
    """The capture of one folder: its own photos or videos; the photos of its subfolders when it
    has none of its own, or with ``recursive``. ``note`` says which subfolders' photos were taken
    or left out."""
    own = sorted(folder.iterdir())
    images = [p for p in own if is_image(p)]
    videos = [p for p in own if is_video(p)]
    if images and videos:
        raise DataError(folder, f"holds both photos ({images[0].name}) and videos ({videos[0].name}): "
                        "pass one kind (several videos may be given as separate arguments)")
    below = list(files_below(folder))
    below_images = [p for p in below if is_image(p)]
    below_videos = [p for p in below if not is_image(p)]
    if videos:
        if recursive and below_images:
            raise DataError(folder, f"holds videos ({videos[0].name}) and its subfolders photos "
                            f"({relative_name(below_images[0], folder)}): pass one kind")
        return Capture("videos", tuple(videos), folder)
    # videos beside photos in an export (a phone's DCIM) are clips of other moments: left out
    videos_left = f"; {_count(len(below_videos), 'video')} there left out" if below_videos else ""
    took_below = bool(below_images) and (recursive or not images)
    note = ""
    if took_below and not images:  # an export's layout (DCIM/100APPLE/...): all the photos are below
        note = (f"note: {folder} holds no photos of its own: taking the {_count(len(below_images), 'photo')} "
                f"found in {_subfolders(folder, below_images)[0]}{videos_left}")
    elif took_below:
        note = (f"note: {folder}: taking its {_count(len(images), 'photo')} and the {len(below_images)} found in "
                f"{_subfolders(folder, below_images)[0]} (--recursive){videos_left}")
    elif below_images and len(images) >= MIN_IMAGES:
        note = (f"note: {folder}: taking its {len(images)} photos; {_count(len(below_images), 'photo')} in "
                f"{_subfolders(folder, below_images)[0]} left out (eg-process --recursive takes them too)")
    elif not images and below_videos:
        shown = ", ".join(relative_name(p, folder) for p in below_videos[:3])
        raise DataError(folder, f"holds no photos or videos of its own, and its subfolders only "
                        f"{_count(len(below_videos), 'video')} ({shown}{', ...' if len(below_videos) > 3 else ''}): "
                        "pass the video files themselves as the inputs")
    if took_below:
        # named by their path below the folder (images/100APPLE/IMG_0001.jpg), posed in that order
        images = sorted(images + below_images, key=lambda p: relative_name(p, folder))
    if len(images) < MIN_IMAGES:
        if took_below:
            more = " (its subfolders' included)"
        elif below_images:
            where, count = _subfolders(folder, below_images)
            more = (f"; {where} hold{'s' if count == 1 else ''} {len(below_images)} more: "
                    "eg-process --recursive takes them")
        else:
            more = ""
        raise DataError(folder, f"holds {len(images)} image(s) ({', '.join(IMAGE_SUFFIXES)}); posing needs at "
                        f"least {MIN_IMAGES} overlapping photos{more}")
    return Capture("images", tuple(images), folder, note)


def find_capture(inputs: list[Path], recursive: bool = False) -> Capture:
    """Classify ``inputs`` (one folder or video, or several videos); bad input is one DataError.
    ``recursive``: a folder's subfolders' photos are taken beside its own."""
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
    return _folder_capture(photo_folder(path), recursive)


def input_key(capture: Capture) -> list[list]:
    """[absolute path, size, modification time] of every input file: what a rerun must match."""
    rows = []
    for path in capture.files:
        info = path.stat()
        rows.append([str(path.resolve()), info.st_size, info.st_mtime_ns])
    return rows
