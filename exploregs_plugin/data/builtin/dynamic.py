"""The built-in dynamic Blur-Trap scene: synchronised cameras over a short clip, with ground truth.

A back wall with a fine mosaic and two striped "bottles" stand behind two moving occluders (a
ball swinging across and a tall block sliding through), under a skyline and a sky. The
occluders cover and uncover the fine texture, so it is seen only part of the time from each
camera: the near side of the Blur Trap in time. The skyline is the far side. Cameras stand on a
fixed arc like a Neu3D rig; ``cam00`` (the arc's centre) is the test camera.

Written in the Neu3D layout (see :mod:`exploregs_plugin.data.neu3d`), so it is read by the same
parser as a captured dataset::

    DIR/poses_bounds.npy, DIR/points3D.ply, DIR/scene.json
    DIR/camNN/images/FFFF.png   frames;  camNN/depths/FFFF.npy  z-depth;  camNN/masks/FFFF.png labels

Region labels per frame (``REGION_LABELS``): ``moving`` where an occluder is hit; ``far`` sky
and content beyond ``far_radius``; ``occluded`` (by motion) static content that an occluder
covers in at least ``occluded_fraction`` of the clip's frames from that camera; ``other``.
Initial points are SfM-like points of the first frame (:func:`scene_render.sparse_points`).
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from PIL import Image

from ..errors import DataError
from ..neu3d import POINTS_FILE, POSES_FILE, viewmat_to_llff
from ..parsed import REGION_LABELS
from .raycast import Box, Cylinder, Dome, Hits, HorizonRing, Lighting, Material, Sphere, pixel_rays, shade, trace
from .layouts import _ground, intrinsics, look_at
from .render import RenderSettings, ViewRender, count_visible, sparse_points
from .textures import Checker, Facades, Mosaic, Sky, Stripes, hash01
from ..transforms_json import write_ply_points

DYNAMIC_GENERATOR_VERSION = 2
"""Bump when the output changes, so cached scenes are regenerated."""


@dataclass(frozen=True)
class DynamicPreset:
    """Everything that defines a built-in dynamic scene."""

    width: int
    height: int
    n_cameras: int
    n_frames: int
    seed: int = 0
    n_points: int = 2500
    supersample: int = 3
    fov_x_deg: float = 60.0
    arc_degrees: float = 50.0
    """The cameras span this arc (a Neu3D rig spans about 60 degrees)."""
    occluded_fraction: float = 0.2
    far_radius: float = 15.0


DYNAMIC_PRESETS: dict[str, DynamicPreset] = {
    "dynamic": DynamicPreset(96, 72, 12, 30),
    "dynamic-tiny": DynamicPreset(48, 36, 4, 6, n_points=600),
}
"""``builtin:dynamic`` (12 cameras x 30 frames at 96x72) and a tiny one for tests."""


class Shifted:
    """A texture carried by a moving object: evaluated in the object's own frame."""

    def __init__(self, texture, offset: np.ndarray) -> None:  # noqa: ANN001 (any texture callable)
        self.texture, self.offset = texture, offset

    def __call__(self, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
        return self.texture(points - self.offset, normals)


def static_world(seed: int) -> list:
    """Ground, a mosaic wall, two striped bottles, a skyline ring (radius 30) and the sky."""
    mosaic_palette = np.array([[0.9, 0.1, 0.1], [0.1, 0.6, 0.9], [0.95, 0.85, 0.1], [0.1, 0.7, 0.3],
                               [0.6, 0.2, 0.7], [0.95, 0.95, 0.95], [0.1, 0.1, 0.1]])
    label = np.array([[0.95, 0.95, 0.9], [0.15, 0.1, 0.1], [0.8, 0.2, 0.1]])
    heights = 3.0 + 6.0 * hash01(np.arange(60)[:, None], seed + 51)

    def skyline(azimuth: np.ndarray) -> np.ndarray:
        return heights[np.floor((azimuth + np.pi) / (2 * np.pi) * 60).astype(np.int64) % 60]

    return [
        _ground(seed),
        Box(np.array([1.6, -1.8, 0.0]), np.array([1.7, 1.8, 1.3]), Material(Mosaic(0.03, mosaic_palette, seed + 52))),
        Cylinder(np.array([1.2, -0.6]), 0.12, 0.0, 0.7, Material(Stripes(np.array([0.0, 0.3, 0.95]), 0.035, label))),
        Cylinder(np.array([1.25, 0.55]), 0.1, 0.0, 0.6, Material(Stripes(np.array([0.0, 0.0, 1.0]), 0.03, label[::-1]),
                                                                 specular=0.3)),
        HorizonRing(30.0, skyline, Material(Facades(60, 1.0, 1.2, seed + 53), lit=False), max_height=9.0),
        Dome(1000.0, Material(Sky(seed + 54), lit=False)),
    ]


def moving_world(time: float, seed: int) -> list:
    """The occluders at ``time`` in [0, 1]: a ball swinging once around the middle (0.7 either
    side), a block sliding 1.4 across, both in front of the wall and the bottles."""
    ball_center = np.array([0.5, 0.7 * np.sin(2 * np.pi * time), 0.55 + 0.15 * np.cos(2 * np.pi * time)])
    ball = Sphere(ball_center, 0.28, Material(Shifted(
        Checker(0.08, np.array([0.95, 0.5, 0.1]), np.array([0.2, 0.1, 0.05]), seed + 61), ball_center)))
    y = -0.7 + 1.4 * time
    lo, hi = np.array([0.9, y - 0.17, 0.0]), np.array([1.1, y + 0.17, 1.05])
    block = Box(lo, hi, Material(Shifted(
        Checker(0.1, np.array([0.2, 0.3, 0.8]), np.array([0.85, 0.85, 0.9]), seed + 62), lo)))
    return [ball, block]


def rig_poses(preset: DynamicPreset) -> list[np.ndarray]:
    """Camera-to-world matrices [4, 4] of the rig: cam00 at the arc's centre, the others
    alternating to its sides (as Neu3D numbers a rig around its central camera)."""
    rng = np.random.default_rng([preset.seed, 2])
    half = np.radians(preset.arc_degrees) / 2
    offsets = [0.0]
    step = half / max((preset.n_cameras - 1 + 1) // 2, 1)
    for k in range(1, preset.n_cameras):
        offsets.append((1 if k % 2 else -1) * step * ((k + 1) // 2))
    poses = []
    for i, offset in enumerate(offsets):
        az = np.pi + offset
        height = 1.0 + 0.25 * (i % 3) / 2 + rng.normal(0.0, 0.02)
        eye = np.array([3.0 * np.cos(az), 3.0 * np.sin(az), height])
        poses.append(look_at(eye, np.array([1.0, 0.0, 0.6]) + rng.normal(0.0, 0.03, 3)))
    return poses


@dataclass
class DynamicScene:
    """A generated clip in memory: images [C, F, H, W, 3], depths [C, F, H, W], labels
    [C, F, H, W] uint8, c2ws [C, 4, 4], K [3, 3], points [P, 3], points_rgb [P, 3]."""

    preset: DynamicPreset
    images: np.ndarray
    depths: np.ndarray
    labels: np.ndarray
    c2ws: np.ndarray
    K: np.ndarray
    points: np.ndarray
    points_rgb: np.ndarray


def _check(preset: DynamicPreset) -> None:
    if preset.n_cameras < 2 or preset.n_frames < 2:
        raise DataError("dynamic preset", f"needs >= 2 cameras and >= 2 frames, got {preset.n_cameras}, "
                        f"{preset.n_frames}")
    if preset.width < 1 or preset.height < 1 or preset.supersample < 1 or preset.supersample % 2 == 0:
        raise DataError("dynamic preset", "width and height must be >= 1 and supersample odd")


def generate_dynamic(preset: DynamicPreset) -> DynamicScene:
    """Render every camera at every frame (deterministic in the seed). The static world is traced
    once per camera; each frame traces only the occluders and keeps whichever hit is nearer."""
    _check(preset)
    s, w, h = preset.supersample, preset.width, preset.height
    K = intrinsics(w, h, preset.fov_x_deg)
    c2ws = np.stack(rig_poses(preset))
    times = np.linspace(0.0, 1.0, preset.n_frames)
    statics = static_world(preset.seed)
    sky_ids = [i for i, p in enumerate(statics) if isinstance(p, Dome)]
    centre = (s * s) // 2  # the sub-sample on the pixel centre
    light = Lighting()
    images = np.zeros((preset.n_cameras, preset.n_frames, h, w, 3))
    depths = np.zeros((preset.n_cameras, preset.n_frames, h, w))
    moving = np.zeros((preset.n_cameras, preset.n_frames, h, w), dtype=bool)
    first_frame: list[ViewRender] = []
    far = np.zeros((preset.n_cameras, h, w), dtype=bool)
    for c, c2w in enumerate(c2ws):
        origin, dirs, z_per_t = pixel_rays(K, c2w, w, h, s)
        hits = trace(origin, dirs, statics)
        base = shade(origin, dirs, hits, statics, light)
        points = origin + np.where(np.isfinite(hits.t), hits.t, 0.0)[:, None] * dirs
        sky = np.isin(hits.prim, sky_ids).reshape(h, w, s * s)[:, :, centre]
        far_rays = np.linalg.norm(points, axis=1) > preset.far_radius
        far[c] = sky | far_rays.reshape(h, w, s * s)[:, :, centre]
        for f, time in enumerate(times):
            prims = moving_world(float(time), preset.seed)
            near = trace(origin, dirs, prims)
            closer = near.t < hits.t
            colors, t = base.copy(), hits.t.copy()
            if closer.any():
                sub = Hits(near.t[closer], near.normals[closer], near.prim[closer])
                colors[closer] = shade(origin, dirs[closer], sub, prims, light)
                t[closer] = near.t[closer]
            images[c, f] = colors.reshape(h, w, s * s, 3).mean(axis=2)
            t_centre = t.reshape(h, w, s * s)[:, :, centre]
            depths[c, f] = t_centre * z_per_t.reshape(h, w, s * s)[:, :, centre]
            moving[c, f] = closer.reshape(h, w, s * s)[:, :, centre]
            if f == 0:
                d = dirs.reshape(h, w, s * s, 3)[:, :, centre]
                hit_points = origin + np.where(np.isfinite(t_centre), t_centre, 0.0)[..., None] * d
                first_frame.append(ViewRender(images[c, 0], depths[c, 0], hit_points, t_centre,
                                              np.linalg.norm(hit_points, axis=-1), sky & ~moving[c, 0]))
    labels = region_labels(moving, far, preset.occluded_fraction)
    points, points_rgb = _first_frame_points(preset, first_frame, c2ws, K, depths[:, 0])
    return DynamicScene(preset, images, depths, labels, c2ws, K, points, points_rgb)


def region_labels(moving: np.ndarray, far: np.ndarray, occluded_fraction: float) -> np.ndarray:
    """uint8 [C, F, H, W] labels from occluder coverage ``moving`` [C, F, H, W] and the static
    far mask ``far`` [C, H, W] (see the module doc)."""
    covered = moving.mean(axis=1, keepdims=True)  # [C, 1, H, W] fraction of frames covered
    labels = np.full(moving.shape, REGION_LABELS["other"], dtype=np.uint8)
    labels[np.broadcast_to(far[:, None], moving.shape)] = REGION_LABELS["far"]
    occluded = np.broadcast_to((covered >= occluded_fraction) & ~far[:, None], moving.shape)
    labels[occluded] = REGION_LABELS["occluded"]
    labels[moving] = REGION_LABELS["moving"]
    return labels


def _first_frame_points(preset: DynamicPreset, views: list[ViewRender], c2ws: np.ndarray, K: np.ndarray,
                        depths: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """SfM-like points of the first frame, from the training cameras (all but cam00)."""
    train = list(range(1, preset.n_cameras))
    w2cs = np.linalg.inv(c2ws)
    Ks = np.repeat(K[None], len(c2ws), axis=0)
    counts = [count_visible(v.points.reshape(-1, 3), Ks[train], w2cs[train], depths[train]).reshape(v.depth.shape)
              for v in views]
    settings = RenderSettings(preset.width, preset.height, preset.supersample, preset.far_radius,
                              n_points=preset.n_points)
    return sparse_points(views, c2ws, train, counts, settings, np.random.default_rng([preset.seed, 3]))


def write_dynamic_scene(scene: DynamicScene, out_dir: Path, seconds: float) -> None:
    """Write ``scene`` into the (new or empty) folder ``out_dir`` in the Neu3D layout."""
    p = scene.preset
    poses = []
    for c, c2w in enumerate(scene.c2ws):
        cam = out_dir / f"cam{c:02d}"
        for sub in ("images", "depths", "masks"):
            (cam / sub).mkdir(parents=True, exist_ok=True)
        for f in range(p.n_frames):
            stem = f"{f:04d}"
            rgb = np.clip(np.round(scene.images[c, f] * 255.0), 0, 255).astype(np.uint8)
            Image.fromarray(rgb).save(cam / "images" / f"{stem}.png")
            np.save(cam / "depths" / f"{stem}.npy", scene.depths[c, f].astype(np.float32))
            Image.fromarray(scene.labels[c, f]).save(cam / "masks" / f"{stem}.png")
        hwf = np.array([[p.height], [p.width], [scene.K[0, 0]]])
        llff = np.concatenate([viewmat_to_llff(np.linalg.inv(c2w)), hwf], axis=1)
        finite = scene.depths[c][np.isfinite(scene.depths[c])]
        poses.append(np.concatenate([llff.reshape(-1), [float(finite.min()), float(finite.max())]]))
    np.save(out_dir / POSES_FILE, np.stack(poses))
    write_ply_points(out_dir / POINTS_FILE, scene.points, scene.points_rgb)
    meta = {"generator_version": DYNAMIC_GENERATOR_VERSION, "preset": asdict(p), "seconds": round(seconds, 3)}
    (out_dir / "scene.json").write_text(json.dumps(meta, indent=1))
