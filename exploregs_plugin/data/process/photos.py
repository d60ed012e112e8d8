"""Photos into the dataset's ``images/``: HEIC through pillow-heif, EXIF orientation applied.

A JPEG or PNG already upright is copied byte for byte (its EXIF focal length then reaches
COLMAP's camera guess); a rotated, HEIC or other photo is written upright as a JPEG that keeps its
EXIF, minus the orientation tag (``ImageOps.exif_transpose`` drops it).
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path, PurePosixPath

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


def output_name(name: str, taken: set[str]) -> str:
    """The dataset's name for the photo named ``name`` (its path below the input folder, ``/``
    between parts; ``taken``: every input's): ``photo.jpg`` as it is when copied, ``photo.jpg``
    for a converted ``photo.heic`` unless another input has that name, in any letter case (then
    ``photo.heic.jpg``): a phone exports ``IMG_0001.HEIC`` beside an edited ``IMG_0001.JPG``, and
    on a case-insensitive disk those two would be one file."""
    path = PurePosixPath(name)
    if path.suffix.lower() in COPIED_SUFFIXES:
        return name
    converted = str(path.with_suffix(".jpg"))
    return converted if converted.lower() not in {t.lower() for t in taken} else f"{name}.jpg"


def import_photo(path: Path, out_dir: Path, name: str) -> tuple[int, int]:
    """Write ``path`` upright as ``out_dir/name`` (atomically; ``name`` may hold subfolders:
    ``100APPLE/IMG_0001.jpg``); returns its (width, height)."""
    image = open_photo(path)
    orientation = image.getexif().get(ORIENTATION_TAG, 1)
    target = out_dir / name
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = target.with_name(f".{target.name}.{os.getpid()}.tmp")
    if path.suffix.lower() in COPIED_SUFFIXES and orientation in (0, 1) and image.mode in ("RGB", "L", "RGBA", "P"):
        shutil.copyfile(path, tmp)
        size = image.size
    else:
        upright = ImageOps.exif_transpose(image)
        exif = upright.info.get("exif")
        upright.convert("RGB").save(tmp, format="JPEG", quality=JPEG_QUALITY, **({"exif": exif} if exif else {}))
        size = upright.size
    os.replace(tmp, target)
    return size
