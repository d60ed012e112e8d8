"""Image files: size checks, reading (RGBA composited on a background), resize and cache paths."""

from __future__ import annotations

import hashlib
import os
import stat
from pathlib import Path

import numpy as np
from PIL import Image, UnidentifiedImageError

from .errors import DataError

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".JPG", ".JPEG", ".PNG")


GRAY_MODES = ("1", "L")
GRAY16_MODES = ("I;16", "I;16L", "I;16B", "I;16N", "I")
"""16-bit grayscale (PNG); Pillow versions before 10 open it as "I" (32-bit integers)."""


def pixel_kind(im: Image.Image, path: Path) -> str:
    """How the pixels of an opened image become RGB: 'rgb' (as they are, or a plain colour
    conversion: palette, CMYK, YCbCr), 'gray' (the value in R, G and B), 'gray16' (16 bits scaled
    to 8, then the same), 'alpha' (composited on a background). DataError for float pixels."""
    if im.mode in ("RGBA", "LA", "PA", "RGBa", "La") or (im.mode == "P" and "transparency" in im.info):
        return "alpha"
    if im.mode in GRAY_MODES:
        return "gray"
    if im.mode in GRAY16_MODES:
        return "gray16"
    if im.mode == "F":
        raise DataError(path, "image has 32-bit float pixels, which have no agreed range; save it as 8- or 16-bit "
                              "RGB or grayscale")
    return "rgb"


def image_info(path: Path) -> tuple[int, int, str]:
    """(width, height, :func:`pixel_kind`) from the file header; DataError when missing or unreadable."""
    if not path.is_file():
        raise DataError(path, "image file is missing")
    try:
        with Image.open(path) as im:
            return im.size[0], im.size[1], pixel_kind(im, path)
    except (UnidentifiedImageError, OSError) as err:
        raise DataError(path, f"image file is unreadable ({err})") from err


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) from the file header; DataError when missing or unreadable."""
    return image_info(path)[:2]


def _gray16_to_rgb(im: Image.Image, path: Path) -> np.ndarray:
    """uint8 [H, W, 3] from 16-bit grayscale: value / 257 (65535 -> 255), in all three channels."""
    values = np.asarray(im, dtype=np.int64)
    if values.min(initial=0) < 0 or values.max(initial=0) > 65535:
        raise DataError(path, f"image has {im.mode} pixels outside 0..65535; save it as 8- or 16-bit RGB or grayscale")
    gray = np.round(values / 257.0).astype(np.uint8)
    return np.repeat(gray[..., None], 3, axis=2)


def read_image_alpha(path: Path, background: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray | None]:
    """(rgb uint8 [H, W, 3], alpha uint8 [H, W, 1] or None). An alpha channel is composited
    over ``background`` [3] in [0, 1] (black when None): rgb = a * rgb + (1 - a) * background,
    and returned too, so a trainer can re-composite on another background. Grayscale puts its
    value in R, G and B (16-bit grayscale scaled to 8 bits first); see :func:`pixel_kind`."""
    try:
        with Image.open(path) as im:
            im.load()
            kind = pixel_kind(im, path)
            if kind == "alpha":
                rgba8 = np.asarray(im.convert("RGBA"), dtype=np.uint8)
                rgba = rgba8.astype(np.float32) / 255.0
                bg = np.zeros(3, np.float32) if background is None else np.asarray(background, np.float32)
                alpha = rgba[..., 3:4]
                rgb = rgba[..., :3] * alpha + bg * (1.0 - alpha)
                return np.clip(np.round(rgb * 255.0), 0, 255).astype(np.uint8), rgba8[..., 3:4].copy()
            if kind == "gray16":
                return _gray16_to_rgb(im, path), None
            return np.asarray(im.convert("RGB"), dtype=np.uint8), None
    except FileNotFoundError as err:
        raise DataError(path, "image file is missing") from err
    except (UnidentifiedImageError, OSError) as err:
        raise DataError(path, f"image file is unreadable ({err})") from err


CONVERSIONS = {
    "gray": ("are grayscale", "the gray value is used for R, G and B"),
    "gray16": ("are 16-bit grayscale", "scaled to 8 bits (value / 257) and used for R, G and B"),
    "alpha": ("have an alpha channel", "composited on the background colour (--datamanager.background)"),
}


def conversion_note(kinds: dict[str, str], skip: tuple[str, ...] = ()) -> str | None:
    """One sentence on the images that are not plain RGB and what is done with them, or None.
    kinds: image name -> :func:`pixel_kind`; ``skip``: kinds the caller reports itself."""
    parts = []
    for kind, (are, done) in CONVERSIONS.items():
        names = [name for name, k in kinds.items() if k == kind]
        if names and kind not in skip:
            parts.append(f"{len(names)} of {len(kinds)} images {are} (e.g. {', '.join(names[:2])}): {done}")
    return "; ".join(parts) or None


def read_image(path: Path, background: np.ndarray | None = None) -> np.ndarray:
    """uint8 [H, W, 3], an alpha channel composited over ``background`` (see read_image_alpha)."""
    return read_image_alpha(path, background)[0]


def resized_size(width: int, height: int, factor: int) -> tuple[int, int]:
    """Size of an image downscaled by an integer ``factor`` (rounded, at least 1 pixel)."""
    return max(1, int(round(width / factor))), max(1, int(round(height / factor)))


def box_downscaled(pixels: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """uint8 [H, W, C] (C 1 or 3) resized to ``size`` = (width, height) with the area (box) filter
    of the --data-factor resize, so a coarse level holds the same pixels a data factor would."""
    mode = "L" if pixels.shape[-1] == 1 else "RGB"
    image = Image.fromarray(np.ascontiguousarray(pixels.reshape(pixels.shape[:2]) if mode == "L" else pixels), mode)
    out = np.asarray(image.resize(size, Image.Resampling.BOX), dtype=np.uint8)
    return out.reshape(out.shape[0], out.shape[1], pixels.shape[-1]).copy()


def resize_to_cache(src: Path, dst: Path, size: tuple[int, int]) -> Path:
    """Resize ``src`` to ``size`` (area filter) into ``dst`` once; later calls reuse ``dst``."""
    if dst.is_file():
        return dst
    try:
        with Image.open(src) as im:
            # JPEG can decode at 1/2, 1/4, 1/8 scale directly (never below ``size``): much faster.
            im.draft("RGB", size)
            im.load()
            out = im.resize(size, Image.Resampling.BOX)
    except FileNotFoundError as err:
        raise DataError(src, "image file is missing") from err
    except (UnidentifiedImageError, OSError) as err:
        raise DataError(src, f"image file is unreadable ({err})") from err
    dst.parent.mkdir(parents=True, exist_ok=True)
    tmp = dst.with_name(f".{dst.name}.{os.getpid()}.tmp{dst.suffix}")
    out.save(tmp, format="PNG" if dst.suffix.lower() == ".png" else None)
    os.replace(tmp, dst)  # atomic: a crash never leaves a half-written cached image
    return dst


def _writable(folder: Path) -> bool:
    """Writable by us and not marked read-only by its mode bits (root ignores the bits, but a
    dataset someone made read-only should stay untouched)."""
    try:
        mode = folder.stat().st_mode
    except OSError:
        return False
    return os.access(folder, os.W_OK) and bool(mode & (stat.S_IWUSR | stat.S_IWGRP | stat.S_IWOTH))


def cache_file_name(rel: str, suffix: str, tag: str = "") -> Path:
    """A path inside a cache folder for dataset image ``rel``: the same relative path when it
    stays inside the dataset, else a hashed flat name (never escapes the cache with ``..``)."""
    path = Path(os.path.normpath(rel))
    stem = path.with_suffix("")
    if path.is_absolute() or ".." in path.parts:
        digest = hashlib.sha1(str(path).encode()).hexdigest()[:10]
        stem = Path(f"{digest}-{path.stem}")
    return stem.with_name(f"{stem.name}{tag}{suffix}")


def source_stamp(path: Path) -> str:
    """A short key of ``path``'s size and modification time: a derived file named with it is
    made again when its source changes (an edited or replaced image is never served stale)."""
    try:
        info = path.stat()
    except OSError as err:
        raise DataError(path, f"image file is unreadable ({err})") from err
    return hashlib.sha1(f"{info.st_size} {info.st_mtime_ns}".encode()).hexdigest()[:8]


def derived_cache_dir(root: Path, what: str, cache_root: Path, beside_data: bool = False) -> Path:
    """Where derived images (resized, undistorted, decoded frames) of dataset ``root`` go.

    By default ``cache_root/derived/<name>-<hash of root's absolute path>/<what>``: a dataset
    folder is never written to. With ``beside_data`` (``--datamanager.cache-beside-data``),
    ``root/.exploregs/<what>`` when the dataset folder is writable, else the default.
    """
    if beside_data and _writable(root):
        return root / ".exploregs" / what
    digest = hashlib.sha1(str(root.resolve()).encode()).hexdigest()[:16]
    return cache_root / "derived" / f"{root.name}-{digest}" / what
