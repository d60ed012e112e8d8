"""The background render thread: which browser view to render next, at which resolution, and
how long to sleep afterwards so rendering stays within its share of the CPU.

A view is re-rendered when its camera, the Gaussian snapshot or the view settings changed
since its last frame. While the camera moves (a camera update less than ``rest_delay``
seconds ago) frames are made at ``moving_resolution``; once it has been still that long, one
sharper frame at ``rest_resolution`` follows.
"""

from __future__ import annotations

import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np
import torch

from exploregs_plugin.cameras import Camera
from exploregs_plugin.viewer.outputs import OutputKind
from exploregs_plugin.viewer.conventions import render_size, viser_to_camera
from exploregs_plugin.viewer.snapshot import Snapshot, SnapshotStore

Quality = Literal["moving", "rest"]
_IDLE_POLL = 0.05
"""Seconds the idle thread waits before looking again (it is woken at once by camera and
settings changes; the poll catches the moving -> rest transition)."""


@dataclass(frozen=True)
class ViewSettings:
    """What every view renders; changed from the GUI."""

    output: OutputKind
    sh_degree: int
    moving_resolution: int
    rest_resolution: int
    rest_delay: float
    max_render_share: float
    time: float = 0.0
    """Dynamic scenes: the time in [0, 1] to show."""


@dataclass(frozen=True)
class BrowserCamera:
    """A browser's camera as viser reports it: camera-to-world ``wxyz`` [4] and ``position``
    [3] (OpenCV axes), vertical ``fov`` in radians, canvas size in pixels."""

    wxyz: np.ndarray
    position: np.ndarray
    fov: float
    width: int
    height: int

    def camera(self, longest_side: int) -> Camera:
        width, height = render_size(self.width, self.height, longest_side)
        return viser_to_camera(self.wxyz, self.position, self.fov, width, height)


class DutyCycle:
    """Sleep accounting that caps the render thread's share of CPU time.

    After ``busy`` seconds of rendering the thread sleeps ``busy (1 - share) / share``, so over
    any run of frames busy / (busy + sleep) = share.
    """

    def __init__(self) -> None:
        self.busy_seconds = 0.0
        self.sleep_seconds = 0.0
        self.frames = 0

    @staticmethod
    def sleep_for(busy: float, share: float) -> float:
        if not 0.0 < share <= 1.0:
            raise ValueError(f"render share must be in (0, 1], got {share}")
        return max(0.0, busy) * (1.0 - share) / share

    def record(self, busy: float, share: float) -> float:
        """Account one frame of ``busy`` seconds; returns the seconds to sleep after it."""
        sleep = self.sleep_for(busy, share)
        self.busy_seconds += max(0.0, busy)
        self.sleep_seconds += sleep
        self.frames += 1
        return sleep


@dataclass
class _View:
    camera: BrowserCamera
    camera_version: int
    moved_at: float
    rendered_key: tuple[int, int, int] | None = None
    rendered_quality: Quality | None = None
    rendered_at: float = float("-inf")


@dataclass(frozen=True)
class Frame:
    """One rendered frame, handed to ``send``."""

    client_id: int
    image: np.ndarray = field(repr=False)  # uint8 [H, W, 3]
    quality: Quality
    step: int
    num_gaussians: int
    camera: BrowserCamera


RenderFn = Callable[[Snapshot, Camera, ViewSettings], np.ndarray]
SendFn = Callable[[Frame], None]


class RenderLoop:
    """Renders the browser views from the latest snapshot, one frame per ``step()``.

    ``render(snapshot, camera, settings) -> uint8 [H, W, 3]`` makes a frame and ``send(frame)``
    delivers it; ``throttled()`` says whether training is running (then the CPU share applies;
    otherwise frames follow each other without sleeping). ``clock`` is injectable for tests.
    """

    def __init__(
        self,
        store: SnapshotStore,
        render: RenderFn,
        send: SendFn,
        settings: ViewSettings,
        throttled: Callable[[], bool],
        clock: Callable[[], float] = time.perf_counter,
    ) -> None:
        self.store = store
        self._render = render
        self._send = send
        self._throttled = throttled
        self._clock = clock
        self._lock = threading.Lock()
        self._views: dict[int, _View] = {}
        self._settings = settings
        self._settings_version = 0
        self._camera_version = 0
        self.duty = DutyCycle()
        self.errors = 0
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    # ------------------------------------------------------------------ inputs (any thread)
    @property
    def settings(self) -> ViewSettings:
        with self._lock:
            return self._settings

    def update_settings(self, **changes: object) -> ViewSettings:
        with self._lock:
            self._settings = replace(self._settings, **changes)  # type: ignore[arg-type]
            self._settings_version += 1
            settings = self._settings
        self._wake.set()
        return settings

    def set_camera(self, client_id: int, camera: BrowserCamera) -> None:
        now = self._clock()
        with self._lock:
            self._camera_version += 1
            view = self._views.get(client_id)
            if view is None:
                self._views[client_id] = _View(camera, self._camera_version, now)
            else:
                view.camera, view.camera_version, view.moved_at = camera, self._camera_version, now
        self._wake.set()

    def remove(self, client_id: int) -> None:
        with self._lock:
            self._views.pop(client_id, None)

    def wake(self) -> None:
        self._wake.set()

    # ------------------------------------------------------------------ one frame
    def _next_job(self, snapshot: Snapshot, now: float) -> tuple[int, _View, Quality, tuple[int, int, int], ViewSettings] | None:
        """The due view that has waited longest, with the quality it needs now."""
        with self._lock:
            best = None
            for client_id, view in self._views.items():
                quality: Quality = "rest" if now - view.moved_at >= self._settings.rest_delay else "moving"
                key = (view.camera_version, snapshot.version, self._settings_version)
                if view.rendered_key == key and (view.rendered_quality == "rest" or quality == "moving"):
                    continue  # this exact frame (or a sharper one) is already on screen
                if best is None or view.rendered_at < best[1].rendered_at:
                    best = (client_id, view, quality, key, self._settings)
            return best

    def step(self) -> float | None:
        """Render the most overdue view once. Returns the seconds to sleep afterwards (the CPU
        share), or None when no view needed a frame."""
        snapshot = self.store.latest()
        if snapshot is None:
            self.store.request()
            return None
        now = self._clock()
        job = self._next_job(snapshot, now)
        if job is None:
            return None
        client_id, view, quality, key, settings = job
        resolution = settings.rest_resolution if quality == "rest" else settings.moving_resolution
        start = self._clock()
        try:
            image = self._render(snapshot, view.camera.camera(resolution), settings)
            self._send(Frame(client_id, image, quality, snapshot.step, snapshot.num_gaussians, view.camera))
        except Exception as err:  # a failed frame must not end the thread (nor training)
            self.errors += 1
            print(f"viewer: render failed ({type(err).__name__}: {err})", file=sys.stderr)
        busy = self._clock() - start
        with self._lock:
            if self._views.get(client_id) is view:
                view.rendered_key, view.rendered_quality, view.rendered_at = key, quality, now
        # The next frame should show newer training progress: ask for a fresh copy.
        self.store.request()
        share = settings.max_render_share if self._throttled() else 1.0
        return self.duty.record(busy, share)

    # ------------------------------------------------------------------ thread
    def _run(self) -> None:
        # Denormal flushing is per thread (the CPU's MXCSR): tiny alphas slow rendering too.
        torch.set_flush_denormal(True)
        while not self._stop.is_set():
            self._wake.clear()
            sleep = self.step()
            if sleep is None:
                self._wake.wait(_IDLE_POLL)
            elif sleep > 0.0:
                self._stop.wait(sleep)

    def start(self) -> None:
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name="exploregs-viewer-render", daemon=True)
            self._thread.start()

    def stop(self, timeout: float = 5.0) -> None:
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout)
            self._thread = None
