"""A small NeRF-synthetic-style scene with real alpha: the built-in scenes' textured objects alone
(no ground, no sky) ray cast from an upper hemisphere and written in the Blender layout.

The only synthetic scene of the shared data (the tiny D-NeRF lego) lost its alpha, so this is
what the RGBA path (compositing, ``--datamanager.background random``) is measured on::

    python -m exploregs_plugin.data.builtin.blender_objects --out /tmp/objects-rgba

writes ``OUT/{train,val,test}/r_NNN.png`` (RGBA: alpha = the share of a pixel's 3x3 sub-samples
that hit an object, colour = their mean colour) and ``OUT/transforms_{train,val,test}.json``
(``camera_angle_x``, OpenGL camera-to-world, ``file_path`` without extension), as Blender does.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np
from PIL import Image

from .raycast import Box, Cylinder, Lighting, Sphere, pixel_rays, shade, trace
from .layouts import build_world, intrinsics, look_at
from ..transforms_json import GL_TO_CV

FOV_X_DEG = 39.6
"""Blender's NeRF-synthetic cameras: camera_angle_x = 0.6911 rad."""
RADIUS = 4.0
"""Camera distance from the objects' centre (NeRF-synthetic: 4.03)."""
CENTRE = np.array([0.0, 0.0, 0.4])
"""Where the cameras look: about the middle of the objects (they stand on z = 0, up to 1 high)."""
SPLITS = (("train", 40), ("val", 8), ("test", 12))


def objects(seed: int) -> list:
    """The textured objects of the built-in ``farside`` layout (a checker box, a striped sphere and
    cylinder, a small box), without its ground, skyline and sky."""
    return [p for p in build_world("farside", seed) if isinstance(p, (Box, Sphere, Cylinder))]


def hemisphere_c2w(rng: np.random.Generator) -> np.ndarray:
    """OpenGL camera-to-world at ``RADIUS`` from ``CENTRE``, uniform azimuth, elevation 10-70 degrees."""
    azimuth, elevation = rng.uniform(0.0, 2 * math.pi), math.radians(rng.uniform(10.0, 70.0))
    eye = CENTRE + RADIUS * np.array([math.cos(azimuth) * math.cos(elevation),
                                      math.sin(azimuth) * math.cos(elevation), math.sin(elevation)])
    return look_at(eye, CENTRE) @ GL_TO_CV  # OpenCV axes -> OpenGL (the inverse flip is the same)


def render_rgba(prims: list, K: np.ndarray, c2w_gl: np.ndarray, width: int, height: int, supersample: int = 3) -> np.ndarray:
    """uint8 [H, W, 4]: straight (not premultiplied) colour of the hits and their coverage as alpha."""
    s2 = supersample * supersample
    origin, dirs, _ = pixel_rays(K, c2w_gl @ GL_TO_CV, width, height, supersample)
    hits = trace(origin, dirs, prims)
    colors = shade(origin, dirs, hits, prims, Lighting()).reshape(height, width, s2, 3)
    hit = (hits.prim >= 0).reshape(height, width, s2, 1)
    count = hit.sum(axis=2)
    rgb = (colors * hit).sum(axis=2) / np.maximum(count, 1)
    rgba = np.concatenate([rgb, count / s2], axis=-1)
    return np.clip(np.round(rgba * 255.0), 0, 255).astype(np.uint8)


def write_blender_objects(out: Path, size: int = 100, seed: int = 0,
                          splits: tuple[tuple[str, int], ...] = SPLITS) -> Path:
    """Write the scene into ``out`` (created; ``size`` x ``size`` pixels, ``splits``: (name, views))."""
    out = Path(out)
    prims = objects(seed)
    K = intrinsics(size, size, FOV_X_DEG)
    rng = np.random.default_rng([seed, 17])
    for split, count in splits:
        (out / split).mkdir(parents=True, exist_ok=True)
        frames = []
        for i in range(count):
            c2w = hemisphere_c2w(rng)
            Image.fromarray(render_rgba(prims, K, c2w, size, size), "RGBA").save(out / split / f"r_{i:03d}.png")
            frames.append({"file_path": f"./{split}/r_{i:03d}", "transform_matrix": c2w.tolist()})
        meta = {"camera_angle_x": math.radians(FOV_X_DEG), "frames": frames}
        (out / f"transforms_{split}.json").write_text(json.dumps(meta, indent=1))
    return out


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, required=True, help="folder to write (created)")
    parser.add_argument("--size", type=int, default=100, help="image width and height in pixels")
    parser.add_argument("--seed", type=int, default=0, help="objects and camera poses")
    args = parser.parse_args()
    print(write_blender_objects(args.out, args.size, args.seed))
