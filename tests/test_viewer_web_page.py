"""The static web page (``exploregs_plugin.viewer.web_page``): its folder and recording, and
the page itself in a real browser (Debian's Chromium driven by Playwright) against our
rasterizer.

The browser test needs ``/usr/bin/chromium`` (``apt-get install -y chromium``) and
``pip install playwright`` (no ``playwright install``: the Debian browser is used); it is
skipped with the reason otherwise. The folder test needs neither.
"""

from __future__ import annotations

import functools
import http.server
import math
import tempfile
import threading
import time
from io import BytesIO
from pathlib import Path
from urllib.parse import urlsplit

import numpy as np
import pytest
import torch
import viser

from exploregs_plugin.cameras import Camera
from exploregs_plugin.io.frames import to_uint8
from exploregs_plugin.model.gaussians import render_camera, rgb_to_sh0
from exploregs_plugin.rasterizer.projection import covariances_3d
from exploregs_plugin.viewer.conventions import intrinsics_from_fov
from exploregs_plugin.viewer.web_page import (
    CLIENT_BUILD,
    RECORDING_NAME,
    read_recording,
    write_web_page,
)

CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_FLAGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
    "--disable-background-networking", "--disable-component-update", "--no-first-run",
]
VIEWPORT = (1024, 640)
FOV_Y = math.radians(60.0)
DISTANCE = 4.0  # the camera stands at z = -4 looking along +z (OpenCV axes: y down)
BACKGROUND = (0.12, 0.14, 0.20)
TIMEOUT = 30.0

# Three Gaussians, apart on screen: (world centre, sigma, colour). The magenta one fills the
# middle; green lies up and right (world -y is up), blue down and left and further away.
SCENE = [
    ((0.0, 0.0, 0.0), 0.6, (0.95, 0.10, 0.85)),
    ((2.58, -1.155, 0.0), 0.25, (0.10, 0.80, 0.20)),
    ((-3.81, 1.625, 2.0), 0.35, (0.15, 0.35, 0.95)),
]
SH1_GREEN = (0.0, 0.0, 0.0, 0.1, -0.2, 0.05, -0.3, 0.1, 0.0)
"""Degree-1 SH of the green Gaussian ([3 coefficients x RGB]): its colour depends on the view,
so the page must show the colour seen from the initial camera."""


def scene_params() -> dict[str, torch.Tensor]:
    n = len(SCENE)
    shN = torch.zeros(n, 3, 3)
    shN[1] = torch.tensor(SH1_GREEN).reshape(3, 3)
    return {
        "means": torch.tensor([c for c, _, _ in SCENE]),
        "scales": torch.tensor([[math.log(s)] * 3 for _, s, _ in SCENE]),
        "quats": torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(n, 1),
        "opacities": torch.full((n,), 8.0),  # sigmoid(8) ~ 0.9997, capped at 0.99 per pixel by us
        "sh0": rgb_to_sh0(torch.tensor([rgb for _, _, rgb in SCENE])),
        "shN": shN,
    }


def camera(width: int, height: int) -> Camera:
    viewmat = torch.eye(4)
    viewmat[2, 3] = DISTANCE  # world-to-camera: z_cam = z + 4
    return Camera(viewmat, intrinsics_from_fov(FOV_Y, width, height), width, height, "cam0")


def splat_message(payload: dict) -> dict:
    splats = [m for _, m in payload["messages"] if m["type"] == "GaussianSplatsMessage"]
    assert len(splats) == 1
    return splats[0]


def test_folder_holds_client_and_recording(tmp_path: Path) -> None:
    params = scene_params()
    # One more Gaussian with a NaN centre: it must be left out, not break the page.
    broken = {k: torch.cat([v, v[:1]]) for k, v in params.items()}
    broken["means"][-1, 0] = float("nan")
    page = write_web_page(tmp_path / "web", broken, sh_degree=1, cameras=[camera(160, 120)],
                          title="Three <blobs>", background=BACKGROUND)
    assert (page.num_gaussians, page.dropped) == (3, 1)
    names = {p.name for p in page.directory.iterdir()}
    client = {p.name for p in CLIENT_BUILD.iterdir()}  # viser 1.1: index.html alone
    assert names == client | {"index.html", RECORDING_NAME, "README.txt"}
    assert page.size_bytes == sum(p.stat().st_size for p in page.directory.iterdir())

    index = page.index.read_text(encoding="utf-8")
    assert f"p.set('playbackPath','{RECORDING_NAME}')" in index  # opens the recording by default
    assert "<title>Three &lt;blobs&gt;</title>" in index
    assert '<div id="root"></div>' in index  # viser's client page itself
    readme = page.readme.read_text(encoding="utf-8")
    assert "python3 -m http.server 8000 --bind 127.0.0.1" in readme and "file://" in readme

    payload, buffers = read_recording(page.recording.read_bytes())
    assert payload["viserVersion"] == viser.__version__
    assert payload["durationSeconds"] == 0.0  # a static scene: the client shows no playback bar
    props = splat_message(payload)["props"]
    raw = buffers[props["buffer"]["__binary_index"]]
    assert props["buffer"]["dtype"] == "<u4" and raw.nbytes == 3 * 32  # 8 words per Gaussian
    words = np.frombuffer(raw, dtype=np.uint32).reshape(3, 8)
    factor = 1.0 / props["scale"]  # the recorded splats are scaled by this, the node undoes it
    assert math.log2(factor) == round(math.log2(factor))  # a power of two: exact in float32
    centres = words[:, :3].view(np.float32) / factor
    np.testing.assert_allclose(centres, params["means"].numpy(), rtol=1e-7, atol=1e-7)
    triu = words[:, 4:7].copy().view(np.float16).astype(np.float32) / factor**2
    cov = covariances_3d(params["quats"], params["scales"].exp()).numpy()
    # float16 keeps 11 significant bits: relative error <= 2^-11.
    np.testing.assert_allclose(triu, cov.reshape(3, 9)[:, [0, 1, 2, 4, 5, 8]], rtol=2.0**-11, atol=1e-7)
    rgba = words[:, 7:8].copy().view(np.uint8)
    np.testing.assert_array_equal(rgba[:, 3], [255, 255, 255])  # round(255 * sigmoid(8))
    # DC colours: 1 level for the float round trip through rgb_to_sh0 (0.1 * 255 = 25.5 rounds
    # either way).
    np.testing.assert_allclose(rgba[[0, 2], :3], to_uint8(np.array([SCENE[0][2], SCENE[2][2]])), atol=1)
    # The green one is view-dependent: its colour is the SH seen from the camera at z = -4,
    # i.e. our render's colour there, not the DC colour.
    dc_green = to_uint8(np.array(SCENE[1][2]))
    ours = to_uint8(render_camera(params, camera(*VIEWPORT), 1, None)[0])
    u, v, _ = screen_discs(*VIEWPORT)[1]
    # Our render there is 0.99 (the alpha cap) of the colour over black: within 3 levels.
    np.testing.assert_allclose(rgba[1, :3], ours[int(v), int(u)], atol=3)
    assert np.abs(rgba[1, :3].astype(int) - dc_green).max() > 10

    messages = {m["type"]: m for _, m in payload["messages"]}
    assert messages["SetCameraPositionMessage"]["position"] == pytest.approx([0.0, 0.0, -DISTANCE])
    assert messages["SetCameraLookAtMessage"]["look_at"] == pytest.approx([0.0, 0.0, 0.0], abs=1e-9)
    assert messages["SetCameraUpDirectionMessage"]["position"] == pytest.approx([0.0, -1.0, 0.0])
    assert messages["SetCameraFovMessage"]["fov"] == pytest.approx(FOV_Y, rel=1e-6)
    assert "BackgroundImageMessage" in messages


def test_float16_range_and_framing_without_cameras(tmp_path: Path) -> None:
    """Gaussians of sigma 1000 (variance 1e6, past float16's 65504) and 1e-3 in one set: the
    recorded covariances stay finite and give back the world ones; without cameras the initial
    view looks at the median from where the robust radius fills the field of view."""
    sigmas = torch.tensor([1000.0, 1.0, 1e-3])
    params = {
        "means": torch.tensor([[0.0, 0.0, 0.0], [5.0, 0.0, 0.0], [0.0, 5.0, 0.0]]),
        "scales": (sigmas[:, None] * torch.tensor([1.0, 0.5, 0.25])).log(),  # anisotropic, rotated
        "quats": torch.tensor([[1.0, 0.2, -0.3, 0.1]]).repeat(3, 1),
        "opacities": torch.zeros(3),
        "sh0": torch.zeros(3, 1, 3),
        "shN": torch.zeros(3, 0, 3),
    }
    page = write_web_page(tmp_path / "web", params, sh_degree=3)
    payload, buffers = read_recording(page.recording.read_bytes())
    props = splat_message(payload)["props"]
    words = np.frombuffer(buffers[props["buffer"]["__binary_index"]], dtype=np.uint32).reshape(3, 8)
    triu = words[:, 4:7].copy().view(np.float16).astype(np.float64)
    assert np.isfinite(triu).all() and np.abs(triu).max() <= 2.0**14
    cov = covariances_3d(params["quats"], params["scales"].exp()).double().numpy().reshape(3, 9)[:, [0, 1, 2, 4, 5, 8]]
    world = triu * props["scale"] ** 2
    # Each entry within float16's rounding (2^-11, doubled for the rescaling) of its row's
    # largest; the sigma 1e-3 one underflows (variance ~1e-6 / 64 < float16's 6e-8) and is not
    # checked.
    assert (np.abs(world[:2] - cov[:2]) <= 2.0**-10 * np.abs(cov[:2]).max(axis=1, keepdims=True)).all()
    rgba = words[:, 7:8].copy().view(np.uint8)
    np.testing.assert_array_equal(rgba[:, 3], [128, 128, 128])  # sigmoid(0) = 0.5
    np.testing.assert_array_equal(rgba[:, :3], [[128] * 3] * 3)  # SH 0: grey 0.5

    messages = {m["type"]: m for _, m in payload["messages"]}
    look_at = np.array(messages["SetCameraLookAtMessage"]["look_at"])
    position = np.array(messages["SetCameraPositionMessage"]["position"])
    np.testing.assert_allclose(look_at, [0.0, 0.0, 0.0], atol=1e-9)  # the median of the means
    assert np.linalg.norm(position - look_at) > 5.0  # the scene (radius ~5) is in front, not around it
    # Clip planes: every Gaussian well inside far (viser culls past it), near far below the
    # distance to the scene.
    reach = np.linalg.norm(params["means"].numpy() - position, axis=1).max()
    assert messages["SetCameraFarMessage"]["far"] >= 2.0 * reach
    assert 0.0 < messages["SetCameraNearMessage"]["near"] < 1e-3 * np.linalg.norm(position - look_at)

    # A log scale of 50 overflows the float32 covariance: that Gaussian is left out.
    huge = {k: v.clone() for k, v in params.items()}
    huge["scales"][0] = 50.0
    assert write_web_page(tmp_path / "huge", huge, sh_degree=0).dropped == 1
    with pytest.raises(ValueError, match="no Gaussian"):
        write_web_page(tmp_path / "empty", {k: v[:0] for k, v in params.items()}, sh_degree=0)


# --------------------------------------------------------------------------- browser


class _QuietHandler(http.server.SimpleHTTPRequestHandler):
    def log_message(self, format: str, *args) -> None:
        pass


def serve(directory: Path) -> http.server.ThreadingHTTPServer:
    """A static server of ``directory`` on a free loopback port, in a daemon thread."""
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(_QuietHandler, directory=str(directory)))
    threading.Thread(target=server.serve_forever, kwargs={"poll_interval": 0.1}, daemon=True).start()
    return server


def screenshot(page) -> np.ndarray:
    from PIL import Image

    return np.asarray(Image.open(BytesIO(page.screenshot())).convert("RGB"))


def screen_discs(width: int, height: int) -> list[tuple[float, float, float]]:
    """(u, v, sigma in pixels) of each Gaussian for a pinhole of vertical fov FOV_Y."""
    focal = 0.5 * height / math.tan(0.5 * FOV_Y)
    out = []
    for (x, y, z), sigma, _ in SCENE:
        depth = z + DISTANCE
        out.append((0.5 * width + focal * x / depth, 0.5 * height + focal * y / depth, focal * sigma / depth))
    return out


def ui_mask(width: int, height: int) -> np.ndarray:
    """Pixels under viser's own overlays: the 'software WebGL' notice (top left) and the
    scene-tree button (top right), with a margin for their shadows."""
    mask = np.zeros((height, width), dtype=bool)
    mask[:170, :330] = True
    mask[:60, width - 60:] = True
    return mask


@pytest.mark.skipif(not CHROMIUM.exists(), reason=f"Chromium not found at {CHROMIUM} (Debian: apt-get install -y chromium)")
def test_page_in_chromium_matches_our_render(tmp_path: Path) -> None:
    sync_api = pytest.importorskip("playwright.sync_api", reason="playwright is not installed (pip install playwright)")
    width, height = VIEWPORT
    params = scene_params()
    page_dir = write_web_page(tmp_path / "web", params, sh_degree=1, cameras=[camera(160, 120)],
                              background=BACKGROUND).directory
    ours = to_uint8(render_camera(params, camera(width, height), 1, torch.tensor(BACKGROUND))[0])
    background = to_uint8(np.array(BACKGROUND))

    server = serve(page_dir)
    origin = f"http://127.0.0.1:{server.server_address[1]}"
    outside: list[str] = []
    try:
        with sync_api.sync_playwright() as pw, tempfile.TemporaryDirectory() as profile:
            browser = pw.chromium.launch_persistent_context(
                profile, executable_path=str(CHROMIUM), args=CHROMIUM_FLAGS, headless=True,
                viewport={"width": width, "height": height},
            )
            try:
                # Offline check: every request of the page and its workers must go to our
                # server (or be a blob: / data: URL the page made itself); anything else is
                # recorded and refused. A websocket (the client's live mode) is recorded too.
                def route(r):
                    url = urlsplit(r.request.url)
                    if url.scheme in ("blob", "data") or f"{url.scheme}://{url.netloc}" == origin:
                        return r.continue_()
                    outside.append(r.request.url)
                    return r.abort()
                browser.route("**/*", route)
                page = browser.new_page()
                page.on("websocket", lambda ws: outside.append(ws.url))
                page.goto(f"{origin}/", timeout=TIMEOUT * 1000)
                shot = wait_for_steady_splats(page, screen_discs(width, height)[0], background)
                assert page.url.endswith(f"?playbackPath={RECORDING_NAME}")
            finally:
                browser.close()
    finally:
        server.shutdown()
        server.server_close()
    assert outside == [], f"the page asked the network for {outside}"
    from PIL import Image

    Image.fromarray(shot).save(tmp_path / "page.png")  # kept for a look when the test fails
    compare(shot, ours, background)


def wait_for_steady_splats(page, disc: tuple[float, float, float], background: np.ndarray) -> np.ndarray:
    """The first of two screenshots 0.5 s apart that agree (the client fades splats in) and show
    the magenta Gaussian's centre off the background."""
    u, v, _ = disc
    deadline = time.monotonic() + TIMEOUT
    previous = None
    while time.monotonic() < deadline:
        shot = screenshot(page)
        lit = np.abs(shot[int(v), int(u)].astype(int) - background).max() > 100
        if lit and previous is not None and np.abs(shot.astype(np.int16) - previous).max() <= 2:
            return shot
        previous = shot.astype(np.int16) if lit else None
        time.sleep(0.5)
    pytest.fail(f"timed out after {TIMEOUT:.0f} s waiting for the splats to render")


def compare(shot: np.ndarray, ours: np.ndarray, background: np.ndarray) -> None:
    """The page against our render of the same camera (tolerances justified inline)."""
    height, width = shot.shape[:2]
    valid = ~ui_mask(width, height)
    ys, xs = np.mgrid[0:height, 0:width]
    discs = screen_discs(width, height)
    radius = np.min([np.hypot(xs + 0.5 - u, ys + 0.5 - v) / s for u, v, s in discs], axis=0)  # in sigmas

    # Not blank, and the Gaussians stand out from the background.
    assert shot[valid].std() > 10.0
    assert np.abs(shot[radius < 0.2].astype(int) - background).max(axis=1).min() > 60
    # Far from every Gaussian the page shows exactly the background (a 1x1 PNG, no blending).
    far = valid & (radius > 3.5)
    assert (np.abs(shot[far].astype(int) - background).max(axis=1) <= 1).mean() > 0.999

    diff = np.abs(shot.astype(int) - ours.astype(int)).max(axis=2)  # [H, W] worst channel
    # Mean colour over each 1-sigma disc. Sources of difference: viser stores colour and opacity
    # in 8 bits (web_page rounds them: <= 0.5 level each), our per-pixel alpha
    # cap of 0.99 (it bites only where alpha > 0.99, r < 0.14 sigma: a sliver of the disc),
    # viser's float16 covariance (2^-11 relative: far below a level) and the 0.3 px^2 low-pass
    # both add (the same). So the means agree within a level; 1.5 allows for another software
    # GL's rounding (measured here: 0.34 at most).
    for (u, v, s), (_, _, rgb) in zip(discs, SCENE):
        disc = valid & (np.hypot(xs + 0.5 - u, ys + 0.5 - v) < s)
        delta = np.abs(shot[disc].mean(axis=0) - ours[disc].mean(axis=0)).max()
        assert delta <= 1.5, f"mean colour over the 1-sigma disc of the {rgb} Gaussian differs by {delta:.2f}"
    # Pixel by pixel within 2.5 sigma (where both draw every fragment): the same sources, plus
    # blending rounding in 8 bits on the GL side; measured p99 1, mean 0.43, max 2 levels.
    inner = valid & (radius < 2.5)
    assert np.percentile(diff[inner], 99) <= 3.0
    assert diff[inner].mean() <= 1.0
    # Coloured masks (more than 16 levels off the background): viser drops a splat's fragments
    # past 2.83 sigma or alpha 0.01, we past alpha 1/255; both are outside where a Gaussian is
    # 16 levels off this background (within ~2.3 sigma), so the masks differ only by edge
    # pixels that round either way: IoU above 0.98 (measured 0.993).
    on_shot = valid & (np.abs(shot.astype(int) - background).max(axis=2) > 16)
    on_ours = valid & (np.abs(ours.astype(int) - background).max(axis=2) > 16)
    iou = (on_shot & on_ours).sum() / max((on_shot | on_ours).sum(), 1)
    assert iou > 0.98, f"IoU of the coloured masks {iou:.4f}"
