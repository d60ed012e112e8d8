"""Geometry and camera paths of the built-in scenes (z up, units of about a metre).

Three layouts, each built to trap standard 3DGS in one way:

* ``farside``: textured objects on a tiled ground, a skyline ring (window grids, radius 60)
  and a rock ridge (radius 150) far beyond, under a sky dome. Cameras sit on a 50 degree arc of
  radius 3.6 and look nearly level, so they move little relative to the distant content (about
  3 units of baseline against 60 to 150 of depth): low parallax, few and noisy SfM points there.
* ``nearside``: a cabinet open on one side whose back panel and floor carry a fine mosaic. Most
  cameras circle the closed sides (azimuth 70 to 290 degrees from the opening) and see the
  mosaic barely or not at all; a few low views face the opening and see it clearly.
* ``combined``: both in one scene (arc cameras of radius 5 behind the cabinet looking at the
  skyline, plus a few views facing the opening).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .raycast import (
    Box,
    Cylinder,
    Dome,
    GroundPlane,
    HorizonRing,
    Material,
    Primitive,
    Sphere,
)
from .textures import Checker, Facades, Mosaic, Rock, Sky, Stripes, Tiles, hash01, value_noise

LAYOUTS = ("farside", "nearside", "combined")

SKYLINE_RADIUS = 60.0
RIDGE_RADIUS = 150.0
SKY_RADIUS = 1000.0


@dataclass
class CameraPose:
    """One generated view: c2w [4, 4] (OpenCV axes in columns) and whether it is a 'clear'
    view of the cabinet interior."""

    c2w: np.ndarray
    clear: bool


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray | None = None) -> np.ndarray:
    """Camera-to-world [4, 4] with OpenCV axes: x right, y down, z towards ``target``."""
    up = np.array([0.0, 0.0, 1.0]) if up is None else up
    forward = target - eye
    forward = forward / max(np.linalg.norm(forward), 1e-12)
    right = np.cross(forward, up)
    norm = np.linalg.norm(right)
    if norm < 1e-9:  # looking straight up or down: any horizontal right vector will do
        right = np.array([1.0, 0.0, 0.0])
    else:
        right = right / norm
    down = np.cross(forward, right)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, down, forward, eye
    return c2w


def _rgb(*values: float) -> np.ndarray:
    return np.array(values, dtype=np.float64)


def _ground(seed: int) -> Primitive:
    palette = np.array([[0.55, 0.5, 0.42], [0.45, 0.42, 0.38], [0.62, 0.58, 0.5], [0.4, 0.45, 0.35]])
    return GroundPlane(0.0, Material(Tiles(0.25, palette, seed)))


def _near_objects(rng: np.random.Generator, seed: int, region_x: tuple[float, float]) -> list[Primitive]:
    """Four textured objects with seeded positions in x within ``region_x`` and |y| < 1.4."""

    def spot() -> np.ndarray:
        return np.array([rng.uniform(*region_x), rng.uniform(-1.3, 1.3)])

    objs: list[Primitive] = []
    p = spot()
    objs.append(Box(np.array([p[0] - 0.3, p[1] - 0.25, 0.0]), np.array([p[0] + 0.3, p[1] + 0.25, 0.55]),
                    Material(Checker(0.12, _rgb(0.85, 0.2, 0.15), _rgb(0.95, 0.9, 0.8), seed + 11))))
    p = spot()
    r = rng.uniform(0.25, 0.35)
    objs.append(Sphere(np.array([p[0], p[1], r]), r,
                       Material(Stripes(np.array([0.3, 0.2, 0.93]), 0.06,
                                        np.array([[0.1, 0.3, 0.8], [0.95, 0.95, 0.3], [0.2, 0.7, 0.3]])),
                                specular=0.3)))
    p = spot()
    objs.append(Cylinder(p, rng.uniform(0.15, 0.22), 0.0, rng.uniform(0.7, 1.0),
                         Material(Stripes(np.array([0.0, 0.0, 1.0]), 0.05,
                                          np.array([[0.9, 0.5, 0.1], [0.2, 0.15, 0.1]])))))
    p = spot()
    objs.append(Box(np.array([p[0] - 0.15, p[1] - 0.15, 0.0]), np.array([p[0] + 0.15, p[1] + 0.15, 0.3]),
                    Material(Checker(0.05, _rgb(0.2, 0.6, 0.9), _rgb(0.1, 0.1, 0.2), seed + 12))))
    return objs


def _cabinet(center_x: float, center_y: float, seed: int) -> list[Primitive]:
    """A cabinet open towards +x: wooden shell, mosaic on the inner back panel and floor."""
    wood = Material(Checker(0.5, _rgb(0.55, 0.38, 0.22), _rgb(0.5, 0.34, 0.2), seed + 21, tint=0.08))
    palette = np.array([[0.9, 0.1, 0.1], [0.1, 0.6, 0.9], [0.95, 0.85, 0.1], [0.1, 0.7, 0.3],
                        [0.6, 0.2, 0.7], [0.95, 0.95, 0.95], [0.1, 0.1, 0.1]])
    mosaic = Material(Mosaic(0.03, palette, seed + 22), specular=0.05)
    x0, x1 = center_x - 0.4, center_x + 0.4  # depth along x; the open side is x1
    y0, y1 = center_y - 0.5, center_y + 0.5
    h, w = 0.8, 0.04
    return [
        Box(np.array([x0, y0, 0.0]), np.array([x1, y1, w]), mosaic),  # floor
        Box(np.array([x0, y0, h - w]), np.array([x1, y1, h]), wood),  # top
        Box(np.array([x0, y0, 0.0]), np.array([x1, y0 + w, h]), wood),  # side
        Box(np.array([x0, y1 - w, 0.0]), np.array([x1, y1, h]), wood),  # side
        Box(np.array([x0, y0, 0.0]), np.array([x0 + w, y1, h]), wood),  # back (outside)
        Box(np.array([x0 + w, y0 + w, w]), np.array([x0 + w + 0.01, y1 - w, h - w]), mosaic),  # back panel
    ]


def _horizon(seed: int) -> list[Primitive]:
    n_buildings = 90
    heights = 4.0 + 10.0 * hash01(np.arange(n_buildings)[:, None], seed + 31)

    def skyline(azimuth: np.ndarray) -> np.ndarray:
        idx = np.floor((azimuth + np.pi) / (2 * np.pi) * n_buildings).astype(np.int64) % n_buildings
        return heights[idx]

    def ridge(azimuth: np.ndarray) -> np.ndarray:
        circle = np.stack([np.cos(azimuth), np.sin(azimuth)], axis=1)
        return 12.0 + 30.0 * value_noise(circle * 3.0, 1.0, seed + 32) + 6.0 * value_noise(circle, 12.0, seed + 33)

    return [
        HorizonRing(SKYLINE_RADIUS, skyline, Material(Facades(n_buildings, 1.2, 1.5, seed + 34), lit=False),
                    max_height=14.0),
        HorizonRing(RIDGE_RADIUS, ridge, Material(Rock(0.15, seed + 35), lit=False), max_height=48.0),
    ]


def build_world(layout: str, seed: int) -> list[Primitive]:
    """All primitives of ``layout`` (one of :data:`LAYOUTS`), deterministic in ``seed``."""
    rng = np.random.default_rng([seed, 1])
    prims: list[Primitive] = [_ground(seed)]
    if layout == "farside":
        prims += _near_objects(rng, seed, (-1.3, 1.3))
    elif layout in ("nearside", "combined"):
        # Objects stay behind the cabinet (x < -0.2) so they never block the clear views.
        prims += _near_objects(rng, seed, (-1.6, -0.6))
        prims += _cabinet(0.3, 0.0, seed)
    else:
        raise ValueError(f"unknown scene layout {layout!r}; expected one of {LAYOUTS}")
    if layout in ("farside", "combined"):
        prims += _horizon(seed)
    prims.append(Dome(SKY_RADIUS, Material(Sky(seed + 41), lit=False)))
    return prims


def view_kinds(n_views: int, test_every: int) -> list[bool]:
    """Which view indices are 'clear' views of the cabinet interior.

    One test view (index ``test_every`` if it exists, else 0) and about 10% of the training
    views (at least 1), spread over the sequence.
    """
    test = [i for i in range(n_views) if test_every > 0 and i % test_every == 0]
    train = [i for i in range(n_views) if i not in test]
    clear = [test[1] if len(test) > 1 else (test[0] if test else 0)]
    n_clear_train = max(1, int(round(0.1 * len(train))))
    if train:
        picks = np.linspace(0, len(train) - 1, n_clear_train + 2)[1:-1].round().astype(int)
        clear += [train[k] for k in picks]
    kinds = [False] * n_views
    for i in clear:
        kinds[i] = True
    return kinds


def camera_path(layout: str, n_views: int, test_every: int, seed: int) -> list[CameraPose]:
    """Seeded camera poses for ``layout``: a sequence like a walk around the scene."""
    rng = np.random.default_rng([seed, 2])
    kinds = view_kinds(n_views, test_every) if layout != "farside" else [False] * n_views
    n_main = sum(1 for k in kinds if not k)
    n_clear = n_views - n_main
    if layout == "nearside":
        main_az = np.radians(np.linspace(70.0, 290.0, max(n_main, 1)))
    else:  # farside / combined: a 50 degree arc on the -x side, looking towards +x
        main_az = np.radians(180.0 + np.linspace(-25.0, 25.0, max(n_main, 1)))
    clear_az = np.radians(np.linspace(-12.0, 12.0, max(n_clear, 1)))
    poses: list[CameraPose] = []
    i_main = i_clear = 0
    for clear in kinds:
        if clear:
            az = clear_az[i_clear] + rng.normal(0.0, np.radians(2.0))
            i_clear += 1
            eye = np.array([0.3 + 2.4 * np.cos(az), 2.4 * np.sin(az), rng.uniform(0.55, 0.8)])
            target = np.array([0.1, 0.0, 0.35]) + rng.normal(0.0, 0.03, 3)
        else:
            az = main_az[i_main] + rng.normal(0.0, np.radians(1.0))
            i_main += 1
            if layout == "nearside":
                radius, height = 3.2 + rng.uniform(-0.2, 0.2), rng.uniform(1.6, 2.2)
                target = np.array([0.0, 0.0, 0.4])
            elif layout == "farside":  # nearly level views: the skyline fills the upper third
                radius, height = 3.6 + rng.uniform(-0.2, 0.2), rng.uniform(0.9, 1.3)
                target = np.array([0.0, 0.0, 0.6])
            else:
                radius, height = 5.0 + rng.uniform(-0.3, 0.3), rng.uniform(1.2, 1.8)
                target = np.array([0.0, 0.0, 0.5])
            eye = np.array([radius * np.cos(az), radius * np.sin(az), height])
            target = target + rng.normal(0.0, 0.05, 3)
        poses.append(CameraPose(look_at(eye, target), clear))
    return poses


def intrinsics(width: int, height: int, fov_x_deg: float) -> np.ndarray:
    """K [3, 3] with square pixels and the principal point at the image centre."""
    if not 1.0 < fov_x_deg < 179.0:
        raise ValueError(f"fov_x_deg must be in (1, 179), got {fov_x_deg}")
    focal = 0.5 * width / np.tan(np.radians(fov_x_deg) / 2)
    return np.array([[focal, 0.0, width / 2], [0.0, focal, height / 2], [0.0, 0.0, 1.0]])
