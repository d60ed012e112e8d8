"""Built-in scenes: presets, generation to disk (COLMAP text through pycolmap) and the cache.

A generated scene is an ordinary COLMAP dataset plus ground truth::

    DIR/images/0000.png ...        rendered views (PNG, 8 bit)
    DIR/sparse/0/*.txt             PINHOLE camera, poses, SfM-like points (COLMAP text)
    DIR/depths/0000.npy ...        float32 [H, W] camera-space z in scene units
    DIR/masks/0000.png ...         uint8 region labels: 0 other, 1 far, 2 occluded
    DIR/split.json                 {"train": [...], "test": [...]} (every 8th view is a test view)
    DIR/scene.json                 preset, settings, seed, generator version, generation time

``builtin:NAME`` generates the preset once into ``$EXPLOREGS_CACHE`` (default
``~/.cache/exploregs/scenes``) and reuses it while ``scene.json`` matches.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import pycolmap
from PIL import Image

from .dynamic import (DYNAMIC_GENERATOR_VERSION, DYNAMIC_PRESETS, DynamicPreset, generate_dynamic,
                              write_dynamic_scene)
from ..cache import cache_root
from ..errors import DataError
from .layouts import LAYOUTS, build_world, camera_path, intrinsics
from .render import RenderSettings, count_visible, region_labels, render_view, sparse_points

GENERATOR_VERSION = 2
"""Bump when the generator's output changes, so cached scenes are regenerated."""



@dataclass(frozen=True)
class ScenePreset:
    """Everything that defines a built-in scene."""

    layout: str
    width: int
    height: int
    n_views: int
    seed: int = 0
    n_points: int = 3000
    supersample: int = 3
    fov_x_deg: float = 60.0
    test_every: int = 8
    occluded_fraction: float = 0.25
    far_radius: float = 15.0


PRESETS: dict[str, ScenePreset] = {
    "tiny": ScenePreset("combined", 64, 48, 10, n_points=400),
    "default": ScenePreset("combined", 144, 108, 32, n_points=3000),
    "farside": ScenePreset("farside", 144, 108, 32, n_points=3000),
    "nearside": ScenePreset("nearside", 144, 108, 32, n_points=3000),
    "combined": ScenePreset("combined", 144, 108, 32, n_points=3000, seed=1),
    "farside-large": ScenePreset("farside", 320, 240, 64, n_points=12000),
    "nearside-large": ScenePreset("nearside", 320, 240, 64, n_points=12000),
    "combined-large": ScenePreset("combined", 320, 240, 64, n_points=12000),
}
"""Preset names for ``builtin:NAME``. ``default`` and ``combined`` share the layout with
different seeds; the ``-large`` presets are the benchmark sizes."""


def _check_preset(preset: ScenePreset) -> None:
    if preset.layout not in LAYOUTS:
        raise DataError("layout", f"unknown layout {preset.layout!r}; expected one of {LAYOUTS}")
    for field in ("width", "height", "n_views", "supersample"):
        if getattr(preset, field) < 1:
            raise DataError(field, f"must be >= 1, got {getattr(preset, field)}")
    if preset.n_views < 2:
        raise DataError("n_views", f"a scene needs at least 2 views, got {preset.n_views}")
    if preset.supersample % 2 == 0:
        raise DataError("supersample", f"must be odd, got {preset.supersample}")
    if preset.n_points < 0:
        raise DataError("n_points", f"must be >= 0, got {preset.n_points}")


def view_names(n_views: int) -> list[str]:
    return [f"{i:04d}.png" for i in range(n_views)]


def split_names(names: list[str], test_every: int) -> tuple[list[str], list[str]]:
    """Every ``test_every``-th name (0, k, 2k, ...) in name order is a test view (0: none)."""
    ordered = sorted(names)
    test = [n for i, n in enumerate(ordered) if test_every > 0 and i % test_every == 0]
    train = [n for n in ordered if n not in set(test)]
    return train, test


@dataclass
class GeneratedScene:
    """A scene in memory (file units). Ks: [V, 3, 3]; c2ws: [V, 4, 4]; images [V, H, W, 3];
    depths [V, H, W]; labels [V, H, W] uint8; points [P, 3]; points_rgb [P, 3]."""

    preset: ScenePreset
    names: list[str]
    Ks: np.ndarray
    c2ws: np.ndarray
    images: np.ndarray
    depths: np.ndarray
    labels: np.ndarray
    points: np.ndarray
    points_rgb: np.ndarray
    train: list[str]
    test: list[str]


def generate(preset: ScenePreset) -> GeneratedScene:
    """Render every view, derive region masks and sparse points (deterministic in the seed)."""
    _check_preset(preset)
    settings = RenderSettings(
        preset.width, preset.height, preset.supersample, preset.far_radius,
        preset.occluded_fraction, preset.n_points,
    )
    prims = build_world(preset.layout, preset.seed)
    poses = camera_path(preset.layout, preset.n_views, preset.test_every, preset.seed)
    K = intrinsics(preset.width, preset.height, preset.fov_x_deg)
    names = view_names(preset.n_views)
    train, test = split_names(names, preset.test_every)
    train_ids = [names.index(n) for n in train]
    views = [render_view(prims, K, pose.c2w, settings) for pose in poses]
    c2ws = np.stack([p.c2w for p in poses])
    w2cs = np.linalg.inv(c2ws)
    Ks = np.repeat(K[None], len(poses), axis=0)
    depths = np.stack([v.depth for v in views])
    labels, seen_counts = [], []
    for view in views:
        counts = count_visible(view.points.reshape(-1, 3), Ks[train_ids], w2cs[train_ids], depths[train_ids])
        counts = counts.reshape(view.depth.shape)
        seen_counts.append(counts)
        labels.append(region_labels(view, counts / max(len(train_ids), 1), settings))
    rng = np.random.default_rng([preset.seed, 3])
    if preset.n_points > 0:
        points, points_rgb = sparse_points(views, c2ws, train_ids, seen_counts, settings, rng)
    else:
        points, points_rgb = np.zeros((0, 3)), np.zeros((0, 3))
    return GeneratedScene(
        preset, names, Ks, c2ws, np.stack([v.image for v in views]), depths,
        np.stack(labels), points, points_rgb, train, test,
    )


def write_colmap_text(
    sparse_dir: Path, names: list[str], Ks: np.ndarray, w2cs: np.ndarray, width: int, height: int,
    points: np.ndarray, points_rgb: np.ndarray,
) -> None:
    """Write PINHOLE cameras, poses and points as a COLMAP text model through pycolmap.

    Ks: [V, 3, 3]; w2cs: [V, 4, 4]; points: [P, 3]; points_rgb: [P, 3] in [0, 1].
    """
    rec = pycolmap.Reconstruction()
    for i, (name, K, w2c) in enumerate(zip(names, Ks, w2cs)):
        cam = pycolmap.Camera(
            model="PINHOLE", width=width, height=height,
            params=[K[0, 0], K[1, 1], K[0, 2], K[1, 2]], camera_id=i + 1,
        )
        rec.add_camera_with_trivial_rig(cam)
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(w2c[:3, :3]), w2c[:3, 3])
        rec.add_image_with_trivial_frame(pycolmap.Image(name=name, camera_id=i + 1, image_id=i + 1), pose)
    colors = np.clip(np.round(points_rgb * 255.0), 0, 255).astype(np.uint8)
    for xyz, rgb in zip(points, colors):
        rec.add_point3D(np.asarray(xyz, dtype=np.float64), pycolmap.Track(), rgb)
    sparse_dir.mkdir(parents=True, exist_ok=True)
    rec.write_text(str(sparse_dir))


def write_scene(scene: GeneratedScene, out_dir: Path, seconds: float) -> None:
    """Write ``scene`` into the (new or empty) directory ``out_dir``."""
    p = scene.preset
    for sub in ("images", "depths", "masks"):
        (out_dir / sub).mkdir(parents=True, exist_ok=True)
    for name, image, depth, label in zip(scene.names, scene.images, scene.depths, scene.labels):
        stem = Path(name).stem
        Image.fromarray(np.clip(np.round(image * 255.0), 0, 255).astype(np.uint8)).save(out_dir / "images" / name)
        np.save(out_dir / "depths" / f"{stem}.npy", depth.astype(np.float32))
        Image.fromarray(label).save(out_dir / "masks" / f"{stem}.png")
    write_colmap_text(
        out_dir / "sparse" / "0", scene.names, scene.Ks, np.linalg.inv(scene.c2ws),
        p.width, p.height, scene.points, scene.points_rgb,
    )
    (out_dir / "split.json").write_text(json.dumps({"train": scene.train, "test": scene.test}, indent=1))
    meta = {"generator_version": GENERATOR_VERSION, "preset": asdict(p), "seconds": round(seconds, 3)}
    (out_dir / "scene.json").write_text(json.dumps(meta, indent=1))


def make_scene(preset: ScenePreset | DynamicPreset, out_dir: Path, overwrite: bool = False) -> Path:
    """Generate ``preset`` (static or dynamic) and write it to ``out_dir`` atomically (temp dir,
    then rename)."""
    out_dir = Path(out_dir).expanduser()
    if out_dir.exists() and any(out_dir.iterdir()):
        if not overwrite:
            raise DataError(out_dir, "directory exists and is not empty (use --overwrite / overwrite=True to replace it)")
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    dynamic = isinstance(preset, DynamicPreset)
    scene = generate_dynamic(preset) if dynamic else generate(preset)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.", dir=out_dir.parent))
    os.chmod(tmp, 0o755)  # mkdtemp makes it private; the scene is an ordinary readable folder
    try:
        (write_dynamic_scene if dynamic else write_scene)(scene, tmp, time.perf_counter() - start)
        if out_dir.exists():
            shutil.rmtree(out_dir)
        os.replace(tmp, out_dir)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return out_dir


def _cached_matches(path: Path, preset: ScenePreset | DynamicPreset) -> bool:
    try:
        meta = json.loads((path / "scene.json").read_text())
    except (OSError, ValueError):
        return False
    version = DYNAMIC_GENERATOR_VERSION if isinstance(preset, DynamicPreset) else GENERATOR_VERSION
    return meta.get("generator_version") == version and meta.get("preset") == asdict(preset)


def preset_by_name(name: str) -> ScenePreset | DynamicPreset:
    presets = {**PRESETS, **DYNAMIC_PRESETS}
    if name not in presets:
        raise DataError(f"builtin:{name}", f"unknown built-in scene; available: {', '.join(presets)}")
    return presets[name]


def ensure_builtin(name: str, cache_dir: Path | None = None, **overrides: object) -> Path:
    """The directory of built-in scene ``name`` (generated on first use, then reused).

    overrides: ScenePreset fields to change (the cache key includes them).
    """
    preset = preset_by_name(name)
    if overrides:
        preset = replace(preset, **overrides)  # type: ignore[arg-type]
    root = Path(cache_dir).expanduser() if cache_dir is not None else cache_root() / "scenes"
    key = name if not overrides else f"{name}-" + "-".join(f"{k}{v}" for k, v in sorted(overrides.items()))
    path = root / key
    if _cached_matches(path, preset):
        return path
    if path.exists():  # stale (older generator or settings) or half-written: replace it
        shutil.rmtree(path, ignore_errors=True)
    try:
        return make_scene(preset, path)
    except (DataError, OSError):
        if _cached_matches(path, preset):  # another process generated it meanwhile
            return path
        raise
