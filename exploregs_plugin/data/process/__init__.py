"""Photos and videos in: pose a capture with pycolmap into a COLMAP dataset (``eg-process``, and
``--data`` given a folder of photos or a video). Modules: ``inputs`` (what the input is),
``photos`` (HEIC, EXIF orientation), ``video`` (sharpest frame per window), ``retrieval`` (pairs
from a vocabulary of the capture's own features), ``sfm`` (pycolmap's stages), ``checks`` (is the
model right), ``progress`` (bars and ``process.log``), ``report`` (report, summary, top-view plot),
``run`` (the resumable stages and the remedies of a model that fails its checks)."""

from .inputs import find_capture, is_capture
from .run import ProcessConfig, is_posed, process_capture

__all__ = ["ProcessConfig", "find_capture", "is_capture", "is_posed", "process_capture"]
