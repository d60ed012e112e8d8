"""Depth maps of a dataset, for the depth loss: read, resized to the image, non-finite pixels masked.

A dataset's ``depth/<image stem>.npy`` holds one float [H, W] map per image (data.md). A pixel with
no depth (sky stored as inf, a hole as NaN, or <= 0) is left out of the depth loss.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
from PIL import Image

from .errors import DataError


def read_depth_map(path: Path, size: tuple[int, int]) -> tuple[np.ndarray, tuple[int, int]]:
    """(float32 [H, W] depth resized (nearest) to ``size`` = (width, height), (masked pixels,
    pixels in the file)).

    Non-finite values (sky stored as inf, holes as NaN) mean "no depth here", as in depth
    datasets: they become 0, which the depth loss leaves out with every value <= 0. DataError
    for a file that is unreadable or not a 2D array.
    """
    try:
        depth = np.load(path)
    except (OSError, ValueError) as err:
        raise DataError(path, f"depth file is unreadable ({err})") from err
    if depth.ndim != 2 or depth.dtype.kind not in "fiu":
        raise DataError(path, f"depth must be a numeric [H, W] array, got shape {depth.shape} of {depth.dtype}")
    depth = depth.astype(np.float32)
    finite = np.isfinite(depth)
    masked = int(depth.size - np.count_nonzero(finite))
    if masked:
        depth = np.where(finite, depth, np.float32(0.0))
    if depth.shape != (size[1], size[0]):
        depth = np.asarray(Image.fromarray(depth).resize(size, Image.Resampling.NEAREST))
    return depth, (masked, int(finite.size))


def warn_masked_depth(masked: dict[Path, tuple[int, int]]) -> None:
    """One warning for every depth map with non-finite pixels: ``masked`` maps a depth file to
    (masked pixels, pixels in the file)."""
    hit = {path: counts for path, counts in masked.items() if counts[0]}
    if not hit:
        return
    pixels = sum(c[0] for c in hit.values())
    total = sum(c[1] for c in masked.values())
    folders = sorted({str(path.parent) for path in hit})
    example = ", ".join(path.name for path in list(hit)[:3])
    warnings.warn(f"{', '.join(folders)}: {pixels} of {total} depth pixels ({100 * pixels / total:.2f}%) in "
                  f"{len(hit)} of {len(masked)} depth maps are not finite (inf or NaN, e.g. sky) and are masked "
                  f"as no depth (e.g. {example})", stacklevel=3)
