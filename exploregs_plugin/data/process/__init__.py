"""Photos and videos in: pose a capture with pycolmap into a COLMAP dataset (``eg-process``, and
``--data`` given a folder of photos or a video). Modules: ``inputs`` (what the input is),
``photos`` (HEIC, EXIF orientation), ``video`` (sharpest frame per window), ``sfm`` (pycolmap's
stages), ``report`` (report, summary, top-view plot), ``run`` (the resumable stages)."""

from .inputs import find_capture, is_capture
from .run import ProcessConfig, is_posed, process_capture

__all__ = ["ProcessConfig", "find_capture", "is_capture", "is_posed", "process_capture"]
