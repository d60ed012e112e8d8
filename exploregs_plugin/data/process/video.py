"""Frames from a video: decoded with PyAV, turned upright by the stream's rotation, and of every
window of consecutive frames only the sharpest kept, so motion-blurred frames are dropped.

Sharpness is the variance of the Laplacian of the grey image: a blurred frame has lost the high
frequencies that the Laplacian (4 c - up - down - left - right) responds to.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Callable

import numpy as np
from PIL import Image

from ..errors import DataError

JPEG_QUALITY = 95
SHARPNESS_WIDTH = 480
"""Sharpness is measured on the frame downscaled to about this width (noise-robust and cheap)."""


def sharpness(rgb: np.ndarray) -> float:
    """Variance of the 4-neighbour Laplacian of the grey image [H, W] from uint8 rgb [H, W, 3]."""
    step = max(1, rgb.shape[1] // SHARPNESS_WIDTH)
    grey = rgb[::step, ::step].astype(np.float32) @ np.array([0.299, 0.587, 0.114], np.float32)
    if grey.shape[0] < 3 or grey.shape[1] < 3:
        return 0.0
    lap = 4.0 * grey[1:-1, 1:-1] - grey[:-2, 1:-1] - grey[2:, 1:-1] - grey[1:-1, :-2] - grey[1:-1, 2:]
    return float(lap.var())


def upright(rgb: np.ndarray, rotation: int) -> np.ndarray:
    """Apply the display matrix's rotation (degrees counter-clockwise, PyAV's ``frame.rotation``)."""
    quarter_turns = int(round(rotation / 90.0)) % 4
    return np.ascontiguousarray(np.rot90(rgb, quarter_turns)) if quarter_turns else rgb


def frame_count(video: Path) -> int:
    """The number of frames the container declares, else duration x rate (0 when neither is known)."""
    import av

    try:
        with av.open(str(video)) as container:
            if not container.streams.video:
                return 0
            stream = container.streams.video[0]
            if stream.frames:
                return int(stream.frames)
            if stream.duration and stream.time_base and stream.average_rate:
                return int(float(stream.duration * stream.time_base) * float(stream.average_rate))
            if container.duration and stream.average_rate:
                return int(container.duration / 1e6 * float(stream.average_rate))
    except av.error.FFmpegError:
        return 0
    return 0


def window_length(total: int, wanted: int) -> int:
    """Frames per window so that ``total`` frames give about ``wanted`` windows (at least 1)."""
    return max(1, math.ceil(total / max(wanted, 1))) if total > 0 else 1


def extract_frames(video: Path, out_dir: Path, prefix: str, wanted: int,
                   on_frame: Callable[[int], None] | None = None) -> list[str]:
    """Write the sharpest frame of each window of ``video`` as ``out_dir/{prefix}NNNNN.jpg``
    (NNNNN its frame index); returns the names. ``on_frame(n)`` reports frames decoded."""
    import av

    window = window_length(frame_count(video), wanted)
    names: list[str] = []

    def keep(best: tuple[float, int, np.ndarray] | None) -> None:
        if best is None:
            return
        name = f"{prefix}{best[1]:05d}.jpg"
        tmp = out_dir / f".{name}.{os.getpid()}.tmp"
        Image.fromarray(best[2]).save(tmp, format="JPEG", quality=JPEG_QUALITY)
        os.replace(tmp, out_dir / name)
        names.append(name)

    best: tuple[float, int, np.ndarray] | None = None
    try:
        with av.open(str(video)) as container:
            if not container.streams.video:
                raise DataError(video, "has no video stream")
            for index, frame in enumerate(container.decode(video=0)):
                rgb = upright(frame.to_ndarray(format="rgb24"), frame.rotation or 0)
                if index % window == 0:
                    keep(best)
                    best = None
                score = sharpness(rgb)
                if best is None or score > best[0]:
                    best = (score, index, rgb)
                if on_frame is not None:
                    on_frame(1)
    except av.error.FFmpegError as err:
        if best is None and not names:
            raise DataError(video, "no decodable video frame") from err
    keep(best)
    if not names:
        raise DataError(video, "no decodable video frame")
    return names
