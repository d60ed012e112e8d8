"""Shared by make_dup.py and make_oracle.py: copy the cached ``builtin:nearside`` scene to a new
folder and read its cameras (not a command)."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pycolmap

from exploregs_plugin.data.builtin.presets import ensure_builtin, write_colmap_text


def copy_nearside(dst: Path) -> tuple[Path, Path]:
    """(source, copy): the cached builtin:nearside (generated on first use, in $EXPLOREGS_CACHE
    like eg-train's) copied to ``dst``, which is replaced if it exists. Refuses a ``dst`` inside
    the source scene or a folder that holds it."""
    src = ensure_builtin("nearside").resolve()
    dst = Path(dst).expanduser().resolve()
    if dst == src or src in dst.parents or dst in src.parents:
        raise SystemExit(f"refusing to write {dst}: it overlaps the cached scene {src}")
    if dst.exists():
        shutil.rmtree(dst)
    shutil.copytree(src, dst)
    return src, dst


def read_cameras(sparse: Path) -> tuple[pycolmap.Reconstruction, list[str], np.ndarray, np.ndarray]:
    """(reconstruction, names, Ks [V, 3, 3], w2cs [V, 4, 4]) of a COLMAP model, in name order."""
    rec = pycolmap.Reconstruction(str(sparse))
    names, Ks, w2cs = [], [], []
    for im in sorted(rec.images.values(), key=lambda im: im.name):
        fx, fy, cx, cy = rec.cameras[im.camera_id].params
        w2c = np.eye(4)
        w2c[:3] = im.cam_from_world().matrix()
        names.append(im.name)
        Ks.append(np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]]))
        w2cs.append(w2c)
    return rec, names, np.stack(Ks), np.stack(w2cs)


def sfm_points(rec: pycolmap.Reconstruction) -> tuple[np.ndarray, np.ndarray]:
    """(xyz [P, 3], rgb [P, 3] in [0, 1]) of the model's points."""
    pts = list(rec.points3D.values())
    return np.array([p.xyz for p in pts]), np.array([p.color for p in pts]) / 255.0


def rewrite_sparse(dst: Path, rec: pycolmap.Reconstruction, names: list[str], Ks: np.ndarray,
                   w2cs: np.ndarray, points: np.ndarray, rgb: np.ndarray) -> None:
    """Replace ``dst/sparse/0`` with these cameras and points (one PINHOLE camera per image)."""
    cam = next(iter(rec.cameras.values()))
    shutil.rmtree(dst / "sparse" / "0")
    write_colmap_text(dst / "sparse" / "0", names, Ks, w2cs, cam.width, cam.height, points, rgb)
