"""eg-process's options, apart from the stages that use them: the command's --help and a config
load without pycolmap, which the stages import."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from ..errors import DataError

Mapper = Literal["incremental", "global"]
"""pycolmap's mappers: incremental (COLMAP's) or global (GLOMAP's averaging)."""


@dataclass
class ProcessConfig:
    """How a capture is posed (eg-process's options; ``--data PHOTOS`` uses the defaults)."""

    num_frames: int = 150
    """Frames kept from the video(s), all videos together: of each window of len / num_frames
    consecutive frames the sharpest. A video with fewer frames keeps them all."""
    max_image_size: int = 1024
    """SIFT runs on images downscaled to at most this many pixels on the long side."""
    matching: Literal["auto", "exhaustive", "sequential", "spatial", "retrieval"] = "auto"
    """Which image pairs are matched. auto: sequential for video frames, exhaustive for fewer than
    60 photos, retrieval from 60 on; retrieval: each photo with its 20 most similar photos by a
    vocabulary of the capture's own SIFT features (and its next 10 in name order when that is the
    capture order); spatial needs GPS positions in the EXIF."""
    mapper: Mapper = "global"
    """global (GLOMAP's rotation and position averaging: a few hundred photos in minutes) or
    incremental (COLMAP's: slower on a large capture)."""
    remedy: bool = True
    """When the model fails its checks (cameras that look away, jumps along the capture order): map
    again from the neighbours' matches only (an ordered capture), then with the other mapper; keep
    the model with the fewest suspect images, leave those out of it, register them again into the
    model without them, and keep the ones that then pass its checks (the rest stay out: one warning)."""
    deterministic: bool = False
    """The same photos give the same model bit for bit on any thread count (bundle adjustment on
    one thread: slower on a large capture)."""
    camera_model: str = "SIMPLE_RADIAL"
    """COLMAP camera model estimated per camera; its distortion is removed when the dataset is read."""
    num_threads: int | None = None
    """Threads of pycolmap's stages (default: one per CPU that other processes leave idle)."""
    verbose: bool = False
    """Show pycolmap's own log lines."""
    recursive: bool = False
    """Also take the photos in the input folder's subfolders, at any depth, beside its own (a
    folder with no photos of its own takes its subfolders' without this); they keep their path
    below it in images/. Hidden folders and those of a dataset or run are passed over."""

    def __post_init__(self) -> None:
        if self.num_frames < 3:
            raise DataError("--num-frames", f"must be >= 3, got {self.num_frames}")
        if self.max_image_size < 64:
            raise DataError("--max-image-size", f"must be >= 64, got {self.max_image_size}")
        if self.num_threads is not None and self.num_threads < 1:
            raise DataError("--num-threads", f"must be >= 1, got {self.num_threads}")
