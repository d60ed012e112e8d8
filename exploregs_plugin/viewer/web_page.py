"""A static web page that shows a Gaussian set with no Python running (``eg-export --format web``).

viser's pip package ships its built browser client (``viser/client/build/index.html``: one
self-contained file, scripts, styles, the zstd decoder and the splat sorter's WebAssembly
inlined). Besides the live websocket mode, that client plays back a *recording* of a scene:
with ``?playbackPath=URL`` in the page address it fetches URL, a ``.viser`` file, and applies
the scene messages it holds (``client/src/App.tsx``, ``FilePlayback.tsx``). A recording is
what ``ViserServer.get_scene_serializer().serialize()`` writes: zstd-compressed msgpack of the
scene messages, with numpy arrays as aligned binary buffers (``viser/infra/_infra.py``).

So ``write_web_page`` starts a ViserServer on a free loopback port (viser has no server-less
scene API; no browser ever connects to it), adds the Gaussians with ``add_gaussian_splats`` and
sets the initial camera, serialises the scene and stops the server. It writes into the folder:

- ``index.html``: viser's client, with a small script ahead of it that adds
  ``playbackPath=scene.viser`` to the address when none is given, so the plain folder URL opens
  the scene;
- ``scene.viser``: the recording;
- ``README.txt``: how to serve the folder.

The client fetches the recording, and browsers refuse ``fetch`` of ``file://`` URLs, so the
page must be served over HTTP (any static server, e.g. ``python -m http.server``); it loads
nothing from the internet (fonts are the system's, the HDR environment and WebAssembly are
inlined; the one remote URL in the client, gstatic's Draco decoder, serves Draco-compressed GLB
meshes, which this page has none of; ``tests/test_viewer_web_page.py`` checks that no request
leaves the server).

viser draws each splat with one RGB colour: the SH are evaluated along the direction from the
initial camera (``sh_degree`` 0: the view-independent DC colour), so the opening view matches
our rasterizer and other views show that view's colours.
"""

from __future__ import annotations

import contextlib
import html
import importlib.util
import io
import math
import shutil
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import msgspec.msgpack
import numpy as np
import torch
import zstandard
from torch import Tensor

from exploregs_plugin.cameras import Camera
from exploregs_plugin.io.frames import to_uint8
from exploregs_plugin.io.ply import PARAM_NAMES, finite_rows
from exploregs_plugin.model.gaussians import activate_detached
from exploregs_plugin.rasterizer.projection import covariances_3d
from exploregs_plugin.rasterizer.sh import sh_colors
from exploregs_plugin.viewer.conventions import (
    camera_forward,
    camera_to_viser,
    camera_up,
    vertical_fov,
)
from exploregs_plugin.viewer.display import available_sh_degree
from exploregs_plugin.viewer.scene import measured_extent

RECORDING_NAME = "scene.viser"
INDEX_NAME = "index.html"
README_NAME = "README.txt"
CLIENT_BUILD = Path(importlib.util.find_spec("viser").origin).resolve().parent / "client" / "build"
"""viser's built client (the folder its own server serves). Found without importing viser, which
loads only when a page is written: eg-export --help does not pay for it."""

SPLATS_NODE = "/gaussians"
DEFAULT_FOV = math.radians(60.0)
"""Vertical field of view of the initial camera when no training camera is given."""
_FRAMING_MARGIN = 1.15
"""Without cameras the initial camera stands where a sphere of this many scene radii just fills
its vertical field of view."""
_F16_MAX_ENTRY = 2.0**14
"""viser stores each covariance entry as float16 (largest finite value 65504; an entry past it
becomes inf, a NaN splat in the browser). Recorded entries are kept at most this large, a factor
4 under that limit."""
_MAX_EXPONENT = 60
"""The float16 rescaling factor is 2^k with |k| <= this: exact in float32, far from its limits."""


@dataclass(frozen=True)
class WebPage:
    """What ``write_web_page`` wrote."""

    directory: Path
    index: Path
    recording: Path
    readme: Path
    num_gaussians: int
    """Gaussians on the page (non-finite ones are left out)."""
    dropped: int
    """Gaussians left out: a parameter was not finite, or the covariance overflowed float32."""
    size_bytes: int
    """Total size of the files written."""
    seconds: float
    """Wall time of the write."""


@dataclass(frozen=True)
class InitialView:
    """The camera the page opens with, in world coordinates (viser's ``initial_camera``)."""

    position: np.ndarray
    look_at: np.ndarray
    up: np.ndarray
    fov: float
    """Vertical field of view in radians."""
    near: float
    far: float
    """Clip planes: viser culls splats outside (near, far) and defaults to 0.01 .. 1000 world
    units, which would clip a small scene at the near plane or a large one at the far plane."""


def write_web_page(
    out_dir: Path,
    params: Mapping[str, Tensor],
    sh_degree: int,
    cameras: Sequence[Camera] | None = None,
    title: str = "ExploreGS scene",
    background: Sequence[float] | Tensor | None = None,
) -> WebPage:
    """Write a static page showing the Gaussians ``params`` into ``out_dir`` (created; files of
    the same names are replaced).

    params: raw parameters (means [N, 3], scales [N, 3] log sigma, quats [N, 4] wxyz,
    opacities [N] logits, sh0 [N, 1, 3], shN [N, K - 1, 3]) in the frame to show.
    sh_degree: degree of the colours baked from the initial view (clipped to what shN holds).
    cameras: the page opens at ``cameras[0]``'s pose and vertical fov, the up direction is their
    mean up; without cameras it looks at the Gaussians' robust bounds from outside.
    background: [3] colour in [0, 1] behind the splats (None: viser's default).
    """
    start = time.perf_counter()
    out_dir = Path(out_dir)
    cameras = list(cameras or [])
    if int(sh_degree) < 0:
        raise ValueError(f"sh_degree must be >= 0, got {sh_degree}")
    total = int(params["means"].shape[0])
    keep = finite_rows(params)  # a NaN centre breaks the browser's depth sort, a NaN covariance its splat
    kept = {name: params[name].detach()[keep.to(params[name].device)] for name in PARAM_NAMES}
    if not bool(keep.any()):
        raise ValueError(f"no Gaussian with finite parameters to show ({total} given)")
    view = initial_view(kept["means"], cameras)
    degree = min(int(sh_degree), available_sh_degree(kept))
    arrays = viser_splats(kept, degree, view.position)
    # A log scale past ~44 overflows the float32 covariance (exp(s)^2 > 3.4e38): left out too.
    finite_cov = np.isfinite(arrays[1]).all(axis=(1, 2))
    centers, covariances, rgbs, opacities = (a[finite_cov] for a in arrays)
    count = int(finite_cov.sum())
    if count == 0:
        raise ValueError(f"no Gaussian with a finite covariance to show ({total} given)")
    exponent = float16_exponent(covariances)
    data = record_scene(centers, covariances, rgbs, opacities, exponent, view, cameras, background)

    out_dir.mkdir(parents=True, exist_ok=True)
    recording = out_dir / RECORDING_NAME
    recording.write_bytes(data)
    index = out_dir / INDEX_NAME
    _copy_client(out_dir, title)
    readme = out_dir / README_NAME
    readme.write_text(_readme(title, count), encoding="utf-8")
    written = [recording, index, readme] + [out_dir / p.relative_to(CLIENT_BUILD)
                                            for p in CLIENT_BUILD.rglob("*") if p.is_file()]
    size = sum(p.stat().st_size for p in set(written))
    return WebPage(out_dir, index, recording, readme, count, total - count, size, time.perf_counter() - start)


def initial_view(means: Tensor, cameras: Sequence[Camera]) -> InitialView:
    """The first camera's pose looking at the scene's median along its own axis (as the live
    viewer starts), or, without cameras, a view from above and aside that frames the
    Gaussians' robust radius (``measured_extent``) around their median. means: [N, 3], finite."""
    points = means.detach().float().cpu()
    centre = points.median(dim=0).values.double().numpy()
    extent = measured_extent(points, cameras)
    if cameras:
        camera = cameras[0]
        _, position = camera_to_viser(camera)
        forward, up = camera_forward(camera), camera_up(camera)
        # Look at the point along the axis level with the median, but never closer than a
        # tenth of the scene radius (a scene behind the camera still gets a valid target).
        distance = max(float(np.dot(centre - position, forward)), 0.1 * extent)
        look_at, fov = position + distance * forward, vertical_fov(camera)
    else:
        direction = np.array([1.0, 1.0, 0.6])  # from above and aside; viser's default up is +z
        distance = _FRAMING_MARGIN * extent / math.sin(0.5 * DEFAULT_FOV)
        position = centre + distance * direction / np.linalg.norm(direction)
        look_at, up, fov = centre, np.array([0.0, 0.0, 1.0]), DEFAULT_FOV
    # far: every Gaussian is within reach of the start, and within reach + 2 distance of any
    # orbit around the target; doubled for zooming out. near: small against the scene, but a
    # positive fraction of it so the depth buffer keeps its precision.
    reach = float(np.linalg.norm(points.double().numpy() - position, axis=1).max())
    far = 2.0 * (reach + 2.0 * distance) + extent
    near = 1e-4 * (distance + extent)
    return InitialView(position, look_at, up, fov, near, far)


def viser_splats(
    params: Mapping[str, Tensor], sh_degree: int, eye: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """What ``add_gaussian_splats`` takes, float32: centres [N, 3], covariances [N, 3, 3]
    (R diag(s^2) R^T, as our rasterizer), colours [N, 3] in [0, 1] (SH of degree ``sh_degree``
    along the direction from ``eye``, clamped as the rasterizer does, then to 1 for 8 bits) and
    opacities [N, 1] (sigmoid of the logits)."""
    means, quats, scales, opacities, sh = activate_detached(params)
    means, quats, scales = means.float().cpu(), quats.float().cpu(), scales.float().cpu()
    eye_t = torch.as_tensor(np.asarray(eye, dtype=np.float32))
    n_coeffs = (sh_degree + 1) ** 2
    rgbs = sh_colors(sh[:, :n_coeffs].float().cpu(), means, eye_t, sh_degree).clamp(max=1.0)
    covariances = covariances_3d(quats, scales)
    return (means.numpy(), covariances.numpy(), rgbs.numpy(),
            opacities.float().cpu().reshape(-1, 1).numpy())


def float16_exponent(covariances: np.ndarray) -> int:
    """k such that the covariances times 4^k (centres times 2^k, undone by a node scale of 2^-k)
    suit viser's float16 storage: the median variance lands near 1, where float16 is densest,
    unless that would push the largest entry past ``_F16_MAX_ENTRY``. Tiny variances may still
    round to zero (the splat is then drawn about one pixel wide, as it nearly is anyway)."""
    if covariances.shape[0] == 0:
        return 0
    variances = np.diagonal(covariances, axis1=1, axis2=2).astype(np.float64)
    positive = variances[variances > 0.0]
    if positive.size == 0:
        return 0
    k = round(-0.5 * math.log2(float(np.median(positive))))
    largest = float(np.abs(covariances).max())
    k = min(k, math.floor(0.5 * math.log2(_F16_MAX_ENTRY / largest)))
    return max(-_MAX_EXPONENT, min(_MAX_EXPONENT, k))


def record_scene(
    centers: np.ndarray,
    covariances: np.ndarray,
    rgbs: np.ndarray,
    opacities: np.ndarray,
    exponent: int,
    view: InitialView,
    cameras: Sequence[Camera],
    background: Sequence[float] | Tensor | None,
) -> bytes:
    """The ``.viser`` recording of a scene holding the splats and the initial camera."""
    factor = 2.0**exponent
    # viser prints its address and "Server stopped" on stdout even when not verbose; nobody is
    # meant to connect to this server, so that text is kept off the export's output.
    import viser

    with contextlib.redirect_stdout(io.StringIO()):
        server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    try:
        scene = server.scene
        if cameras:
            up = np.mean([camera_up(c) for c in cameras], axis=0)
            if np.linalg.norm(up) > 1e-3:  # opposed cameras: keep viser's default up
                scene.set_up_direction(up / np.linalg.norm(up))
        if background is not None:
            colour = np.asarray(torch.as_tensor(background, dtype=torch.float32).cpu(), dtype=np.float32)
            if colour.shape != (3,):
                raise ValueError(f"web page background must be [3], got {colour.shape}")
            # A 1x1 PNG (lossless, unlike JPEG) stretched behind the scene.
            scene.set_background_image(to_uint8(colour.reshape(1, 1, 3)), format="png")
        scene.add_gaussian_splats(
            SPLATS_NODE,
            centers=(centers * np.float32(factor)).astype(np.float32),
            covariances=(covariances * np.float32(factor * factor)).astype(np.float32),
            # Rounded to 8 bits here: viser's own conversion truncates.
            rgbs=to_uint8(rgbs),
            opacities=to_uint8(opacities),
            scale=1.0 / factor,
        )
        initial = server.initial_camera
        initial.position = tuple(float(v) for v in view.position)
        initial.look_at = tuple(float(v) for v in view.look_at)
        initial.up = tuple(float(v) for v in view.up)
        initial.fov = float(view.fov)
        initial.near = float(view.near)
        initial.far = float(view.far)
        return server.get_scene_serializer().serialize()
    finally:
        with contextlib.redirect_stdout(io.StringIO()):
            server.stop()


def read_recording(data: bytes) -> tuple[dict, list[memoryview]]:
    """Decode a ``.viser`` recording: (payload, binary buffers). The payload holds
    ``messages`` [(time, message dict)], ``durationSeconds``, ``viserVersion``; numpy arrays in
    the messages are ``{"__binary_index": i, "dtype": ...}`` placeholders into the buffers.
    (The format of ``StateSerializer.serialize``: [8-byte size][zstd([8-byte msgpack length]
    [msgpack][8-byte-aligned buffers])].)"""
    if len(data) < 8:
        raise ValueError("not a viser recording: shorter than its 8-byte header")
    size = int.from_bytes(data[:8], "little")
    inner = zstandard.ZstdDecompressor().decompress(data[8:], max_output_size=size)
    if len(inner) != size:
        raise ValueError(f"viser recording decompressed to {len(inner)} bytes, its header says {size}")
    length = int.from_bytes(inner[:8], "little")
    payload = msgspec.msgpack.decode(inner[8:8 + length])
    buffers, offset = [], 8 + length
    for nbytes in payload.get("binaryBufferLengths", ()):
        offset += (8 - offset % 8) % 8
        buffers.append(memoryview(inner)[offset:offset + nbytes])
        offset += nbytes
    return payload, buffers


def _copy_client(out_dir: Path, title: str) -> None:
    """Copy viser's client build into ``out_dir`` with its index opening the recording."""
    for source in CLIENT_BUILD.rglob("*"):
        target = out_dir / source.relative_to(CLIENT_BUILD)
        if source.is_dir():
            target.mkdir(parents=True, exist_ok=True)
        elif source.name != INDEX_NAME:
            shutil.copy2(source, target)
    page = (CLIENT_BUILD / INDEX_NAME).read_text(encoding="utf-8")
    head = page.find("<head>")
    if head < 0 or "<title>" not in page:
        raise RuntimeError(f"viser's client page {CLIENT_BUILD / INDEX_NAME} has no <head> or <title>")
    # Runs before the client (which starts after decompressing itself): the plain folder URL
    # gets ?playbackPath=scene.viser, an explicit playbackPath is kept.
    opener = (
        "<script>(function(){var p=new URLSearchParams(location.search);"
        f"if(!p.has('playbackPath')){{p.set('playbackPath','{RECORDING_NAME}');"
        "history.replaceState(null,'',location.pathname+'?'+p.toString()+location.hash);}})();</script>"
    )
    at = head + len("<head>")
    page = page[:at] + opener + page[at:]
    start, end = page.index("<title>") + len("<title>"), page.index("</title>")
    page = page[:start] + html.escape(title) + page[end:]
    (out_dir / INDEX_NAME).write_text(page, encoding="utf-8")


def _readme(title: str, count: int) -> str:
    import viser

    return (
        f"{title}: {count:,} Gaussians, shown by viser {viser.__version__}'s web client (no Python needed).\n"
        "\n"
        "Serve this folder over HTTP; from inside it:\n"
        "\n"
        "    python3 -m http.server 8000 --bind 127.0.0.1\n"
        "\n"
        "then open http://127.0.0.1:8000/ (any static web server works; the page needs no internet).\n"
        f"Opening {INDEX_NAME} as a file (file://) does not work: browsers refuse to fetch\n"
        f"{RECORDING_NAME} from a file:// page.\n"
        "\n"
        "Drag to orbit, right-drag to pan, scroll to zoom. The colours are those seen from the\n"
        "initial view (one colour per Gaussian).\n"
    )
