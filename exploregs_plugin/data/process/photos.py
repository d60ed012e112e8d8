"""Photos into the dataset's ``images/``: HEIC through pillow-heif, EXIF orientation applied.

A JPEG or PNG already upright is copied byte for byte (its EXIF focal length then reaches
COLMAP's camera guess); a rotated, HEIC or other photo is written upright as a JPEG that keeps its
EXIF, minus the orientation tag (``ImageOps.exif_transpose`` drops it).
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

from PIL import Image, ImageOps

from ..errors import DataError

ORIENTATION_TAG = 0x0112
COPIED_SUFFIXES = (".jpg", ".jpeg", ".png")
JPEG_QUALITY = 95


def register_heif() -> bool:
    """Let PIL open HEIC / HEIF photos when pillow-heif is installed; False when it is not."""
    try:
        from pillow_heif import register_heif_opener
    except ImportError:
        return False
    register_heif_opener()
    return True


def open_photo(path: Path) -> Image.Image:
    """The decoded photo (fully loaded, so a truncated file fails here); one DataError if unreadable."""
    heif = register_heif()
    if path.suffix.lower() in (".heic", ".heif") and not heif:
        raise DataError(path, "HEIC photo, but pillow-heif is not installed (pip install pillow-heif)")
    try:
        image = Image.open(path)
        image.load()
    except (OSError, ValueError, Image.DecompressionBombError) as err:
        raise DataError(path, f"cannot read this image ({err})") from err
    return image


def output_name(path: Path, taken: set[str]) -> str:
    """``photo.jpg`` as it is when copied, ``photo.jpg`` for a converted ``photo.heic`` unless
    another input has that name (then ``photo.heic.jpg``)."""
    if path.suffix.lower() in COPIED_SUFFIXES:
        return path.name
    name = f"{path.stem}.jpg"
    return name if name not in taken else f"{path.name}.jpg"


def import_photo(path: Path, out_dir: Path, name: str) -> tuple[int, int]:
    """Write ``path`` upright as ``out_dir/name`` (atomically); returns its (width, height)."""
    image = open_photo(path)
    orientation = image.getexif().get(ORIENTATION_TAG, 1)
    tmp = out_dir / f".{name}.{os.getpid()}.tmp"
    if path.suffix.lower() in COPIED_SUFFIXES and orientation in (0, 1) and image.mode in ("RGB", "L", "RGBA", "P"):
        shutil.copyfile(path, tmp)
        size = image.size
    else:
        upright = ImageOps.exif_transpose(image)
        exif = upright.info.get("exif")
        upright.convert("RGB").save(tmp, format="JPEG", quality=JPEG_QUALITY, **({"exif": exif} if exif else {}))
        size = upright.size
    os.replace(tmp, out_dir / name)
    return size
