"""Writing a sequence of rendered cameras as PNG frames (and an MP4 when a video writer is installed).

Three kinds of frame: ``rgb`` (the colour image on the background), ``alpha`` (accumulated
opacity as grey) and ``depth`` (expected depth, colour-mapped between one ``near`` and ``far``
for the whole sequence so a video does not flicker; pixels the scene barely covers are black).
"""

from __future__ import annotations

import importlib.util
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Literal, Sequence

import numpy as np
from PIL import Image

from exploregs_plugin.cameras import Camera

RenderMode = Literal["rgb", "depth", "alpha"]
DEPTH_PERCENTILES = (1.0, 99.0)
"""Automatic near/far: these percentiles of the covered pixels' depths (robust to stray Gaussians)."""


@dataclass
class RenderedSequence:
    """What :func:`render_sequence` wrote; ``near``/``far`` only for depth (in output units)."""

    frames: list[Path]
    video: Path | None
    video_note: str | None
    near: float | None = None
    far: float | None = None


def to_uint8(image: np.ndarray) -> np.ndarray:
    """Float image [H, W, C] in [0, 1] -> uint8 (values outside are clipped)."""
    return (np.clip(image, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def depth_range(
    depths: Sequence[np.ndarray], alphas: Sequence[np.ndarray], alpha_min: float = 0.5
) -> tuple[float, float]:
    """(near, far): the 1st and 99th percentile of depth over pixels with alpha >= ``alpha_min``.

    depths, alphas: one [H, W] array per frame. With no covered pixel, (0, 1). A degenerate
    range (near == far) is widened so that normalising never divides by zero.
    """
    covered = [d[(a >= alpha_min) & np.isfinite(d)] for d, a in zip(depths, alphas)]
    values = np.concatenate(covered) if covered else np.zeros(0)
    if values.size == 0:
        return 0.0, 1.0
    near, far = (float(v) for v in np.percentile(values, DEPTH_PERCENTILES))
    if far - near <= 1e-12 * max(abs(near), 1.0):
        pad = max(abs(near) * 1e-3, 1e-6)
        near, far = near - pad, far + pad
    return near, far


def colorize_depth(
    depth: np.ndarray, alpha: np.ndarray, near: float, far: float, cmap: str = "turbo", alpha_min: float = 0.5
) -> np.ndarray:
    """Depth [H, W] -> uint8 RGB [H, W, 3]: (depth - near) / (far - near), clipped to [0, 1],
    through a matplotlib colour map; pixels with alpha < ``alpha_min`` are black."""
    import matplotlib

    if not far > near:
        raise ValueError(f"depth range needs far > near, got near={near}, far={far}")
    try:
        colormap = matplotlib.colormaps[cmap]
    except KeyError as err:
        raise ValueError(f"unknown colour map {cmap!r} (any matplotlib name, e.g. turbo, viridis)") from err
    t = np.clip((np.nan_to_num(depth, nan=far) - near) / (far - near), 0.0, 1.0)
    rgb = colormap(t)[..., :3]
    rgb[alpha < alpha_min] = 0.0
    return to_uint8(rgb)


VIDEO_CRF = 18
"""H.264 constant rate factor of the MP4s: visually lossless for renders (0 = lossless)."""


def video_writer_status() -> str | None:
    """None when MP4s can be written (PyAV, FFmpeg's encoders, a dependency), else why not."""
    if importlib.util.find_spec("av") is None:
        return "no MP4 written: PyAV is not installed (pip install av); PNG frames only"
    return None


class _VideoSink:
    """Appends frames to an H.264 MP4 through PyAV; frames are padded to even sides (yuv420p
    needs them)."""

    def __init__(self, path: Path, fps: float) -> None:
        import av
        from fractions import Fraction

        self.path = path
        self.container = av.open(str(path), mode="w")
        self.stream = self.container.add_stream("libx264", rate=Fraction(fps).limit_denominator(1001))
        self.stream.pix_fmt = "yuv420p"
        self.stream.options = {"crf": str(VIDEO_CRF)}
        self._sized = False

    def append(self, frame: np.ndarray) -> None:
        import av

        h, w = frame.shape[:2]
        frame = np.ascontiguousarray(np.pad(frame, ((0, h % 2), (0, w % 2), (0, 0)), mode="edge"))
        if not self._sized:
            self.stream.width, self.stream.height = frame.shape[1], frame.shape[0]
            self._sized = True
        for packet in self.stream.encode(av.VideoFrame.from_ndarray(frame, format="rgb24")):
            self.container.mux(packet)

    def close(self) -> None:
        if self._sized:
            for packet in self.stream.encode():  # flush the encoder's delayed frames
                self.container.mux(packet)
        self.container.close()


ViewRenderer = Callable[[Camera], tuple[np.ndarray, np.ndarray, np.ndarray]]
"""Renders one camera: image [H, W, 3], alpha [H, W], depth [H, W] (numpy, float)."""


def render_sequence(
    render: ViewRenderer,
    cameras: Sequence[Camera],
    out_dir: Path,
    *,
    mode: RenderMode = "rgb",
    fps: float = 30.0,
    video: bool = True,
    near: float | None = None,
    far: float | None = None,
    depth_scale: float = 1.0,
    cmap: str = "turbo",
    alpha_min: float = 0.5,
    on_frame: Callable[[int, int], None] | None = None,
) -> RenderedSequence:
    """Render every camera with ``render`` and write ``out_dir/frame_XXXXX.png`` (+
    ``out_dir/<mode>.mp4``).

    depth: expected depth times ``depth_scale`` (e.g. 1 / normalisation scale for the dataset's
    units), colour-mapped between ``near`` and ``far``; either left None is taken from the
    rendered depths (:func:`depth_range`). ``on_frame(i, n)`` is called after each render.
    """
    if mode not in ("rgb", "depth", "alpha"):
        raise ValueError(f"unknown render mode {mode!r}; choose rgb, depth or alpha")
    if not cameras:
        raise ValueError("no cameras to render")
    if not fps > 0:
        raise ValueError(f"fps must be > 0, got {fps}")
    if near is not None and far is not None and not far > near:
        raise ValueError(f"depth range needs far > near, got near={near}, far={far}")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    note = video_writer_status() if video else None
    sink = None
    if video and note is None:
        try:
            sink = _VideoSink(out_dir / f"{mode}.mp4", fps)
        except Exception as err:  # e.g. an ffmpeg binary that does not run here: frames still work
            note = f"no MP4 written: the video writer failed to start ({type(err).__name__}: {err}); PNG frames only"
    frames: list[Path] = []
    pending: list[tuple[np.ndarray, np.ndarray]] = []  # depth mode: (depth, alpha) until the range is known

    def emit(frame: np.ndarray) -> None:
        path = out_dir / f"frame_{len(frames):05d}.png"
        Image.fromarray(frame).save(path)
        frames.append(path)
        if sink is not None:
            sink.append(frame)

    try:
        for i, camera in enumerate(cameras):
            image, alpha, depth = render(camera)
            if mode == "rgb":
                emit(to_uint8(image))
            elif mode == "alpha":
                emit(to_uint8(np.repeat(alpha[..., None], 3, axis=2)))
            elif near is not None and far is not None:  # fixed range: no need to hold the depths
                emit(colorize_depth(depth * depth_scale, alpha, near, far, cmap, alpha_min))
            else:
                pending.append((depth * depth_scale, alpha))
            if on_frame is not None:
                on_frame(i, len(cameras))
        if pending:
            auto_near, auto_far = depth_range([d for d, _ in pending], [a for _, a in pending], alpha_min)
            near = auto_near if near is None else near
            far = auto_far if far is None else far
            for depth, alpha in pending:
                emit(colorize_depth(depth, alpha, near, far, cmap, alpha_min))
    finally:
        if sink is not None:
            sink.close()
    # frames left from an earlier, longer render into the same folder would join this sequence
    written = set(frames)
    for stale in out_dir.glob("frame_[0-9][0-9][0-9][0-9][0-9].png"):
        if stale not in written:
            stale.unlink()
    return RenderedSequence(frames, sink.path if sink is not None else None, note,
                            near if mode == "depth" else None, far if mode == "depth" else None)
