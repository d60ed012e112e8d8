"""The live viewer: a viser server showing the training cameras, the initial points and the
current Gaussians rendered by our CPU rasterizer from each browser's camera.

Threads: the training thread calls ``update`` / ``wait_if_paused`` / ``finish`` (it alone
reads the live parameters, at step boundaries); viser's threads deliver camera and GUI
events; one render thread (``RenderLoop``) renders from published snapshots.
"""

from __future__ import annotations

import math
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np
import torch
import viser
from torch import Tensor

from exploregs_plugin.cameras import Camera
from exploregs_plugin.viewer.outputs import OUTPUT_KINDS
from exploregs_plugin.viewer.conventions import camera_forward, camera_to_viser, camera_up, vertical_fov
from exploregs_plugin.io.frames import to_uint8
from exploregs_plugin.viewer.display import render_frame
from exploregs_plugin.viewer.render_loop import BrowserCamera, Frame, RenderLoop, ViewSettings
from exploregs_plugin.viewer.scene import ViewerScene, scene_centre
from exploregs_plugin.viewer.settings import ViewerSettings
from exploregs_plugin.viewer.snapshot import SnapshotStore


_RECENT_STEPS = 20
"""Train PSNR and seconds per iteration are averaged over this many recent steps."""
_STATS_INTERVAL = 0.25
"""Seconds between stats refreshes sent to the browser (steps can be much faster)."""
_FRUSTUM_COLOR = (40, 90, 200)
_FRUSTUM_FRACTION = 0.03  # default frustum length: this x scene extent
_POINT_FRACTION = 0.003  # default point size: this x scene extent
_COVER_LENGTHS = 4.0
"""A training camera's thumbnail ahead of the view and nearer than this many frustum lengths would
cover part of it (at a 60 degree field of view, a sixth of the height or more): it is hidden."""


def _forward_of(wxyz: np.ndarray) -> np.ndarray:
    """The world direction a viser camera looks along: the third column (OpenCV +z) of R(wxyz)."""
    w, x, y, z = (float(v) for v in wxyz)
    return np.array([2.0 * (x * z + w * y), 2.0 * (y * z - w * x), 1.0 - 2.0 * (x * x + y * y)])


def _evenly_spaced(count: int, limit: int) -> set[int]:
    """Up to ``limit`` indices spread evenly over range(count)."""
    if count <= 0 or limit <= 0:
        return set()
    if limit >= count:
        return set(range(count))
    return {int(round(x)) for x in np.linspace(0, count - 1, limit)}


def thumbnail_image(image: Tensor, height: int) -> np.ndarray:
    """Area-downscaled uint8 copy of ``image`` [H, W, 3] in [0, 1] with the given height."""
    h, w = int(image.shape[0]), int(image.shape[1])
    if h < 1 or w < 1:
        raise ValueError(f"thumbnail source image is empty: {tuple(image.shape)}")
    new_h = min(height, h)
    new_w = max(1, int(round(w * new_h / h)))
    small = torch.nn.functional.interpolate(
        image[..., :3].permute(2, 0, 1)[None].float(), size=(new_h, new_w), mode="area"
    )[0].permute(1, 2, 0)
    return to_uint8(small.numpy())


class Viewer:
    """Serves one scene; see ``ViewerSettings`` for the settings (``ViewerConfig.setup`` builds the
    viewer) and ``docs/viewer.md``.

    training=True: ``update`` is called after each step, and the GUI has a pause control.
    training=False: a fixed scene (``eg-view``); frames are rendered without CPU throttling.
    """

    def __init__(self, config: ViewerSettings, scene: ViewerScene, training: bool = True) -> None:
        self.config = config
        self.scene = scene
        self.training = training
        self.store = SnapshotStore()
        self.store.offer(scene.params(), scene.step, force=True, field=self._field())
        self._step = scene.step
        self._num_gaussians = self.store.latest().num_gaussians  # type: ignore[union-attr]
        self._status = "waiting for the first step" if training else "fixed scene"
        self._recent: deque[tuple[float, float]] = deque(maxlen=_RECENT_STEPS)
        self._last_update: float | None = None
        self._last_stats_push = 0.0
        self._pause = threading.Condition()
        self._paused = False
        self._running = False  # training steps are being made (the CPU share applies)
        self._closed = False
        self._frame_lock = threading.Lock()
        self.frames_sent = 0
        self.last_frame: Frame | None = None  # the latest frame sent to any browser

        self.server = viser.ViserServer(host=config.host, port=config.port, label="ExploreGS", verbose=False)
        self.port = int(self.server.get_port())
        shown_host = "localhost" if config.host in ("0.0.0.0", "::", "") else config.host
        self.url = f"http://{shown_host}:{self.port}"

        max_degree = scene.max_sh_degree
        degree = max_degree if config.sh_degree is None else min(config.sh_degree, max_degree)
        self.loop = RenderLoop(
            self.store,
            self._render,
            self._send,
            ViewSettings(config.output, degree, config.moving_resolution, config.rest_resolution,
                         config.rest_delay, config.max_render_share),
            throttled=lambda: self._running,
        )
        self._frustum_scale = config.frustum_scale or _FRUSTUM_FRACTION * scene.extent
        self._frustums: list[Any] = []
        self._thumbnail_centres = np.zeros((0, 3))  # [N, 3] centre of each frustum's image
        self._covering: set[int] = set()  # frustums hidden because they would cover the view
        self._frustum_lock = threading.RLock()  # camera and click callbacks arrive on viser's pool
        self._show_cameras = True
        self._points: Any = None
        try:
            self._add_scene()
            self._add_gui()
        except BaseException:
            self.server.stop()  # do not leave a server thread holding the port
            raise
        self.server.on_client_connect(self._on_connect)
        self.server.on_client_disconnect(lambda client: self.loop.remove(client.client_id))
        self.loop.start()
        print(f"viewer: {self.url}  ({scene.name}, {self._num_gaussians} Gaussians)", file=sys.stderr)

    # ------------------------------------------------------------------ scene content
    def _add_scene(self) -> None:
        scene, cfg = self.scene, self.config
        cameras = list(scene.cameras)
        if cameras:
            up = np.mean([camera_up(c) for c in cameras], axis=0)
            if np.linalg.norm(up) > 1e-3:
                self.server.scene.set_up_direction(up / np.linalg.norm(up))
        with_thumbnail = _evenly_spaced(len(cameras), cfg.max_thumbnails if scene.thumbnail else 0)
        for i, camera in enumerate(cameras):
            wxyz, position = camera_to_viser(camera)
            image = thumbnail_image(scene.thumbnail(i), cfg.thumbnail_height) if (
                scene.thumbnail is not None and i in with_thumbnail) else None
            handle = self.server.scene.add_camera_frustum(
                f"/cameras/{i:05d}", fov=vertical_fov(camera), aspect=camera.width / camera.height,
                scale=self._frustum_scale, thickness=1.5, thickness_units="screen",
                color=_FRUSTUM_COLOR, image=image, wxyz=wxyz, position=position,
            )
            handle.on_click(lambda event, index=i: self.jump_to_camera(event.client, index))
            self._frustums.append(handle)
        self._thumbnail_centres = np.array([camera_to_viser(c)[1] + self._frustum_scale * camera_forward(c)
                                            for c in cameras]).reshape(-1, 3)
        if scene.points is not None and scene.points.shape[0] > 0 and cfg.max_points > 0:
            stride = max(1, math.ceil(scene.points.shape[0] / cfg.max_points))
            points = scene.points[::stride].detach().float().cpu().numpy()
            rgb = (scene.points_rgb[::stride].detach().float().cpu().numpy() if scene.points_rgb is not None
                   else np.full((len(points), 3), 0.5))
            self._points = self.server.scene.add_point_cloud(
                "/initial_points", points, to_uint8(rgb), point_size=cfg.point_size or _POINT_FRACTION * scene.extent,
            )
            self._points.visible = cfg.show_points
        self._set_initial_camera(cameras)

    def _set_initial_camera(self, cameras: list[Camera]) -> None:
        """Start where the first training camera stands (its frustum and any other close ahead
        hidden, since their thumbnails would cover the view); without cameras, look at the scene
        from outside."""
        initial = self.server.initial_camera
        centre = scene_centre(self.scene)
        if cameras:
            camera = cameras[0]
            _, position = camera_to_viser(camera)
            forward, up = camera_forward(camera), camera_up(camera)
            distance = max(float(np.dot(centre - position, forward)), 0.1 * self.scene.extent)
            initial.position = tuple(position)
            initial.look_at = tuple(position + distance * forward)
            initial.up = tuple(up)
            initial.fov = vertical_fov(camera)
            self._hide_covering(position, forward)
        else:
            direction = np.array([1.0, 1.0, 0.6])  # from above and aside (viser's default up is +z)
            initial.position = tuple(centre + 2.5 * self.scene.extent * direction / np.linalg.norm(direction))
            initial.look_at = tuple(centre)

    def _hide_covering(self, position: np.ndarray, forward: np.ndarray) -> None:
        """Hide the frustums whose thumbnails would cover part of a view from ``position`` looking
        along ``forward`` (ahead of it and within _COVER_LENGTHS frustum lengths: the one it looks
        through and its close neighbours); show again those that no longer would."""
        offset = self._thumbnail_centres - np.asarray(position, dtype=np.float64)
        ahead = offset @ np.asarray(forward, dtype=np.float64) > 0.0
        near = np.linalg.norm(offset, axis=1) < _COVER_LENGTHS * self._frustum_scale
        covering = set(np.nonzero(ahead & near)[0].tolist())
        with self._frustum_lock:
            for i in covering ^ self._covering:
                self._frustums[i].visible = self._show_cameras and i not in covering
            self._covering = covering

    def jump_to_camera(self, client: viser.ClientHandle, index: int) -> None:
        """Move ``client``'s view to training camera ``index`` (what a frustum click does)."""
        camera = self.scene.cameras[index]
        wxyz, position = camera_to_viser(camera)
        self._hide_covering(position, camera_forward(camera))  # first, so no thumbnail flashes across the view
        with client.atomic():
            client.camera.fov = vertical_fov(camera)
            client.camera.wxyz = wxyz
            client.camera.position = position

    # ------------------------------------------------------------------ GUI
    def _add_gui(self) -> None:
        gui, settings = self.server.gui, self.loop.settings
        if self.training:
            self._pause_button = gui.add_button("Pause training", icon=viser.Icon.PLAYER_PAUSE)
            self._pause_button.on_click(lambda _: self.set_paused(not self._paused))
        with gui.add_folder("Stats"):
            self._stats = gui.add_markdown(self._stats_text())
        with gui.add_folder("Render"):
            output = gui.add_dropdown("Output", OUTPUT_KINDS, initial_value=settings.output)
            output.on_update(lambda _: self.loop.update_settings(output=output.value))
            degree = gui.add_slider("SH degree", 0, self.scene.max_sh_degree, 1, settings.sh_degree,
                                    disabled=self.scene.max_sh_degree == 0)
            degree.on_update(lambda _: self.loop.update_settings(sh_degree=int(degree.value)))
            rest = gui.add_slider("Resolution (still)", 64, 2048, 16, settings.rest_resolution,
                                  hint="Longest side in pixels once the camera stops")
            rest.on_update(lambda _: self.loop.update_settings(rest_resolution=int(rest.value)))
            moving = gui.add_slider("Resolution (moving)", 32, 1024, 16, settings.moving_resolution,
                                    hint="Longest side in pixels while the camera moves")
            moving.on_update(lambda _: self.loop.update_settings(moving_resolution=int(moving.value)))
            share = gui.add_slider("Max render CPU share", 0.05, 1.0, 0.05, settings.max_render_share,
                                   hint="Share of CPU time the viewer may use while training runs")
            share.on_update(lambda _: self.loop.update_settings(max_render_share=float(share.value)))
            if self.scene.deformation is not None:  # a dynamic scene: which moment to show
                moment = gui.add_slider("Time", 0.0, 1.0, 0.01, settings.time,
                                        hint="Time in the clip (0 = first frame, 1 = last)")
                moment.on_update(lambda _: self.loop.update_settings(time=float(moment.value)))
            cams = gui.add_checkbox("Show cameras", True)
            cams.on_update(lambda _: self._set_cameras_visible(bool(cams.value)))
            if self._points is not None:
                pts = gui.add_checkbox("Show initial points", self.config.show_points)
                pts.on_update(lambda _: setattr(self._points, "visible", bool(pts.value)))

    def _set_cameras_visible(self, visible: bool) -> None:
        with self._frustum_lock:
            self._show_cameras = visible
            for i, handle in enumerate(self._frustums):
                handle.visible = visible and i not in self._covering

    def _stats_text(self) -> str:
        if self._recent:
            seconds = sum(s for s, _ in self._recent) / len(self._recent)
            psnrs = [p for _, p in self._recent if math.isfinite(p)]
            psnr = f"{sum(psnrs) / len(psnrs):.2f} dB" if psnrs else "n/a"
            timing = f"{seconds:.3f}"
        else:
            psnr, timing = "n/a", "n/a"
        return (
            f"**Status:** {self._status}  \n**Iteration:** {self._step}  \n"
            f"**Gaussians:** {self._num_gaussians:,}  \n**Train PSNR:** {psnr}  \n"
            f"**Seconds / iteration:** {timing}  \n"
            f"<small>PSNR and timing: mean of the last {_RECENT_STEPS} steps</small>"
        )

    def _push_stats(self, force: bool = False) -> None:
        now = time.monotonic()
        if force or now - self._last_stats_push >= _STATS_INTERVAL:
            self._last_stats_push = now
            self._stats.content = self._stats_text()

    # ------------------------------------------------------------------ browser cameras and frames
    async def _on_connect(self, client: viser.ClientHandle) -> None:
        # Registered on the event loop, before viser dispatches this client's first camera
        # message to camera callbacks, so the first camera is not missed.
        client.camera.on_update(lambda camera: self._on_camera(client.client_id, camera))

    def _on_camera(self, client_id: int, camera: viser.CameraHandle) -> None:
        state = BrowserCamera(np.array(camera.wxyz, dtype=np.float64), np.array(camera.position, dtype=np.float64),
                              float(camera.fov), int(camera.image_width), int(camera.image_height))
        if state.width < 1 or state.height < 1 or not 0.0 < state.fov < math.pi:
            return  # the browser has not laid out its canvas yet
        self.loop.set_camera(client_id, state)
        self._hide_covering(state.position, _forward_of(state.wxyz))

    def _render(self, snapshot: Any, camera: Camera, settings: ViewSettings) -> np.ndarray:
        return render_frame(snapshot, camera, settings.output, settings.sh_degree, self.scene.background,
                            self.scene.raster_settings, settings.time)

    def _field(self) -> Any:
        """A dynamic scene's live deformation field (None for a static one)."""
        return self.scene.deformation() if self.scene.deformation is not None else None

    def _send(self, frame: Frame) -> None:
        client = self.server.get_clients().get(frame.client_id)
        if client is None:
            self.loop.remove(frame.client_id)
            return
        client.scene.set_background_image(frame.image, format="jpeg", jpeg_quality=self.config.jpeg_quality)
        with self._frame_lock:
            self.frames_sent += 1
            self.last_frame = frame

    # ------------------------------------------------------------------ training-thread hooks
    def update(self, step: int, stats: Mapping[str, Any] | None = None, seconds: float | None = None) -> None:
        """After a training step: ``step`` = steps done, ``stats`` = the step's stats (``psnr``
        is read), ``seconds`` = its duration (unset: time since the previous call). Copies the
        parameters only when the render thread asked for a newer snapshot."""
        now = time.perf_counter()
        if seconds is None:
            seconds = now - self._last_update if self._last_update is not None else float("nan")
        self._last_update = now
        self._step = int(step)
        self._running = not self._paused
        self._status = "training"
        psnr = float((stats or {}).get("psnr", float("nan")))
        if math.isfinite(seconds):
            self._recent.append((float(seconds), psnr))
        params = self.scene.params()
        self._num_gaussians = int(params["means"].shape[0])
        if self.store.offer(params, step, field=self._field()):
            self.loop.wake()
        self._push_stats()

    @property
    def paused(self) -> bool:
        return self._paused

    def set_paused(self, paused: bool) -> None:
        """Pause or resume training (the GUI button calls this)."""
        with self._pause:
            self._paused = bool(paused) and self.training
            self._pause.notify_all()
        if self.training:
            self._pause_button.label = "Resume training" if self._paused else "Pause training"
            self._pause_button.icon = viser.Icon.PLAYER_PLAY if self._paused else viser.Icon.PLAYER_PAUSE

    def wait_if_paused(self, should_stop: Callable[[], bool] | None = None) -> None:
        """Call at a step boundary: returns at once unless paused; while paused it blocks
        (still serving snapshots, so the view stays current) until resumed, the viewer is
        closed, or ``should_stop()`` turns true (e.g. Ctrl-C)."""
        if not self._paused:
            return
        self._running = False
        self._status = "paused"
        self._push_stats(force=True)
        while True:
            with self._pause:
                if not self._paused or self._closed:
                    break
                self._pause.wait(0.1)
            if self.store.offer(self.scene.params(), self._step):
                self.loop.wake()
            if should_stop is not None and should_stop():
                break
        self._status = "training"
        self._push_stats(force=True)

    def finish(self, step: int | None = None, should_stop: Callable[[], bool] | None = None) -> None:
        """Training ended: show the final state; with ``serve_after_training`` keep serving
        until Ctrl-C (or ``should_stop()``)."""
        self._running = False
        if step is not None:
            self._step = int(step)
        params = self.scene.params()
        self._num_gaussians = int(params["means"].shape[0])
        self.store.offer(params, self._step, force=True, field=self._field())
        self.loop.wake()
        self._status = "finished"
        self._push_stats(force=True)
        if self.config.serve_after_training:
            print(f"viewer: training finished; still serving {self.url} (Ctrl-C to stop)", file=sys.stderr)
            self.serve_forever(should_stop)

    def publish(self, params: Mapping[str, Tensor], step: int | None = None) -> None:
        """Show a different fixed Gaussian set (for eg-view-like uses and tests)."""
        if step is not None:
            self._step = int(step)
        self.store.offer(params, self._step, force=True)
        self._num_gaussians = int(params["means"].shape[0])
        self.loop.wake()
        self._push_stats(force=True)

    def serve_forever(self, should_stop: Callable[[], bool] | None = None) -> None:
        """Block until Ctrl-C, ``should_stop()`` or ``close()``."""
        try:
            while not self._closed and not (should_stop is not None and should_stop()):
                time.sleep(0.2)
        except KeyboardInterrupt:
            pass

    def close(self) -> None:
        """Stop the render thread and the server (idempotent); a paused trainer resumes."""
        if self._closed:
            return
        with self._pause:
            self._closed = True
            self._paused = False
            self._pause.notify_all()
        self.loop.stop()
        self.server.stop()

    def __enter__(self) -> "Viewer":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
