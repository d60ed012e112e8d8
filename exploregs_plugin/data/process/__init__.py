"""Photos and videos in: pose a capture with pycolmap into a COLMAP dataset (``eg-process``, and
``--data`` given a folder of photos or a video). Modules: ``inputs`` (what the input is),
``photos`` (HEIC, EXIF orientation), ``video`` (sharpest frame per window), ``retrieval`` (pairs
from a vocabulary of the capture's own features), ``sfm`` (pycolmap's stages), ``checks`` (is the
model right), ``progress`` (bars and ``process.log``), ``report`` (report, summary, top-view plot),
``config`` (eg-process's options), ``run`` (the resumable stages and the remedies of a model that fails its checks, the second chance of its suspect images)."""

from ...runtime.lazy_names import lazy_names
from .config import ProcessConfig
from .inputs import find_capture, is_capture

# the stages import pycolmap: they load when a capture is posed, not for eg-process --help
__getattr__ = lazy_names(__name__, {"is_posed": ".run", "process_capture": ".run"})

__all__ = ["ProcessConfig", "find_capture", "is_capture", "is_posed", "process_capture"]
