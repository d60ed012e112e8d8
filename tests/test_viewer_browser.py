"""The live viewer in a real browser: Debian's Chromium driven by Playwright.

A scene holds one large magenta Gaussian straight in front of the initial camera. The page is
loaded, a sharp ("rest") frame rendered by our rasterizer is awaited, and the screenshot must
show magenta over the disc where the Gaussian is nearly opaque and nowhere far from it. The
Gaussian is then removed: the magenta must go while a training-camera frustum (green
thumbnail) stays visible, so viser's own scene elements cannot pass the test on their own.
Finally a click on that thumbnail must move the browser's camera to that training camera.

Needs ``/usr/bin/chromium`` (``apt-get install -y chromium``) and ``pip install playwright``
(no ``playwright install``: the Debian browser is used); skipped with the reason otherwise.
"""

from __future__ import annotations

import math
import tempfile
import time
from io import BytesIO
from pathlib import Path

import numpy as np
import pytest
import torch

from exploregs_plugin.cameras import Camera
from exploregs_plugin.model.gaussians import rgb_to_sh0
from exploregs_plugin.viewer import ViewerConfig, ViewerScene
from exploregs_plugin.viewer.conventions import intrinsics_from_fov

CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_FLAGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
    "--disable-background-networking", "--disable-component-update", "--no-first-run",
]
if not CHROMIUM.exists():
    pytest.skip(f"Chromium not found at {CHROMIUM} (Debian: apt-get install -y chromium)", allow_module_level=True)
sync_api = pytest.importorskip("playwright.sync_api", reason="playwright is not installed (pip install playwright)")

VIEWPORT = (1024, 640)
FOV_Y = math.radians(60.0)
DISTANCE = 4.0  # camera 0 stands at z = -4 looking along +z at the Gaussian in the origin
SIGMA = 0.6  # world standard deviation of the Gaussian
MAGENTA = (0.95, 0.1, 0.85)
THUMB_GREEN = (0.1, 0.8, 0.2)
TIMEOUT = 30.0
CAMERA_1 = (-1.6, 0.8, -1.5)  # a second training camera whose frustum is in view, lower left


def gaussians(count: int) -> dict[str, torch.Tensor]:
    return {
        "means": torch.zeros(count, 3),
        "scales": torch.full((count, 3), math.log(SIGMA)),
        "quats": torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(count, 1),
        "opacities": torch.full((count,), 8.0),  # sigmoid(8) ~ 0.9997, capped at 0.99 per pixel
        "sh0": rgb_to_sh0(torch.tensor([MAGENTA])).repeat(count, 1, 1),
        "shN": torch.zeros(count, 0, 3),
    }


def camera_at(x: float, y: float, z: float) -> Camera:
    viewmat = torch.eye(4)
    viewmat[:3, 3] = torch.tensor([-x, -y, -z])  # looks along +z, OpenCV axes
    return Camera(viewmat, intrinsics_from_fov(FOV_Y, 160, 120), 160, 120, f"cam({x},{y},{z})")


def magenta_mask(shot: np.ndarray) -> np.ndarray:
    """Pixels that are the Gaussian's colour at alpha >= ~0.4 over black (red and blue high
    and alike, green low)."""
    r, g, b = (shot[..., i].astype(np.float32) for i in range(3))
    return (r > 90) & (b > 80) & (g < 0.4 * np.minimum(r, b)) & (np.abs(r - b) < 0.35 * np.maximum(r, b))


def green_mask(shot: np.ndarray) -> np.ndarray:
    r, g, b = (shot[..., i].astype(np.float32) for i in range(3))
    return (g > 120) & (r < 0.5 * g) & (b < 0.5 * g)


def screenshot(page) -> np.ndarray:
    from PIL import Image

    return np.asarray(Image.open(BytesIO(page.screenshot())).convert("RGB"))


def steady(a: np.ndarray, b: np.ndarray) -> bool:
    """Two screenshots show the same picture (the browser has finished any transition)."""
    return bool(np.abs(a.astype(np.int16) - b.astype(np.int16)).max() <= 3)


def wait_for(condition, what: str):
    deadline = time.monotonic() + TIMEOUT
    while time.monotonic() < deadline:
        result = condition()
        if result is not None:
            return result
        time.sleep(0.25)
    pytest.fail(f"timed out after {TIMEOUT:.0f} s waiting for {what}")


def test_gaussian_rendered_in_chromium() -> None:
    scene = ViewerScene.from_params(gaussians(1), cameras=[camera_at(0.0, 0.0, -DISTANCE), camera_at(*CAMERA_1)])
    scene.thumbnail = lambda i: torch.tensor(THUMB_GREEN).expand(120, 160, 3)
    viewer = ViewerConfig(port=0, frustum_scale=0.6, rest_resolution=512).setup(scene, training=False)
    try:
        with sync_api.sync_playwright() as pw, tempfile.TemporaryDirectory() as profile:
            browser = pw.chromium.launch_persistent_context(
                profile, executable_path=str(CHROMIUM), args=CHROMIUM_FLAGS, headless=True,
                viewport={"width": VIEWPORT[0], "height": VIEWPORT[1]},
            )
            try:
                page = browser.new_page()
                page.goto(viewer.url)
                check_gaussian_then_removed(page, viewer)
            finally:
                browser.close()
    finally:
        viewer.close()


def check_gaussian_then_removed(page, viewer) -> None:
    width, height = VIEWPORT
    # Where the Gaussian must appear: the browser starts at camera 0's pose with its vertical
    # fov, so the origin projects to the canvas centre and one sigma spans f * SIGMA / DISTANCE.
    focal = 0.5 * height / math.tan(0.5 * FOV_Y)
    sigma_px = focal * SIGMA / DISTANCE
    ys, xs = np.mgrid[0:height, 0:width]
    radius = np.hypot(xs + 0.5 - width / 2, ys + 0.5 - height / 2) / sigma_px  # in sigmas
    core = radius < 1.0  # alpha >= 0.99 exp(-1/2) = 0.6: clearly magenta
    far = radius > 2.5  # alpha < 0.05: background (also holds viser's frustum, gizmo, panel)
    # Magenta (r > 90 of ~242) where alpha > ~0.37, i.e. within 1.4 sigma.
    expected_area = math.pi * (1.4 * sigma_px) ** 2

    shots: list[tuple[object, np.ndarray]] = []

    def rest_frame_with_gaussian():
        frame = viewer.last_frame  # a sharp frame of the initial view (the browser may report
        # intermediate cameras while it applies the initial position and fov)
        if frame is None or frame.quality != "rest" or abs(frame.camera.fov - FOV_Y) > 1e-3 \
                or not np.allclose(frame.camera.position, (0.0, 0.0, -DISTANCE), atol=1e-3):
            return None
        shots.append((frame, screenshot(page)))
        if len(shots) < 2 or shots[-2][0] is not frame or not steady(shots[-2][1], shots[-1][1]):
            return None  # the browser is still bringing this frame on screen
        shot = shots[-1][1]
        return shot if magenta_mask(shot)[core].mean() > 0.95 else None

    shot = wait_for(rest_frame_with_gaussian, "a sharp frame showing the magenta Gaussian")
    assert max(viewer.last_frame.image.shape) == 512  # rendered at the rest resolution (longest side)
    mask = magenta_mask(shot)
    assert mask[core].mean() > 0.95
    assert mask[far].mean() < 0.002, "magenta far from the Gaussian: not our render"
    assert 0.6 * expected_area < mask.sum() < 1.5 * expected_area

    # Remove the Gaussian: the colour must vanish, while viser's scene (frustum with its green
    # thumbnail) stays on screen.
    frames_before = viewer.frames_sent
    viewer.publish(gaussians(0))

    def frame_without_gaussian():
        if viewer.frames_sent <= frames_before:
            return None
        shot = screenshot(page)
        return shot if magenta_mask(shot).mean() < 0.001 else None

    shot = wait_for(frame_without_gaussian, "the magenta to disappear after removing the Gaussian")
    assert magenta_mask(shot)[core].mean() < 0.01
    green = green_mask(shot)
    assert green.sum() > 200, "the training-camera frustum thumbnail should be visible"

    # Clicking that frustum's thumbnail moves the browser's camera to training camera 1.
    ys, xs = np.nonzero(green)
    page.mouse.click(float(xs.mean()), float(ys.mean()))
    client = next(iter(viewer.server.get_clients().values()))
    target = np.array(CAMERA_1)

    def jumped():
        # The one we look through is hidden, the one we left is shown again.
        frustums = [h.visible for h in viewer._frustums]
        return True if np.allclose(client.camera.position, target, atol=1e-3) and frustums == [True, False] else None

    wait_for(jumped, "the view to jump to the clicked training camera (and swap the hidden frustum)")
