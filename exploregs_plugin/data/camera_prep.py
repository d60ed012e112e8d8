"""From a camera of any model to a pinhole ``K`` for the image file actually used.

Shared by the COLMAP and transforms.json parsers: choose the image at the requested
``data_factor`` (``images_N/`` or a cached resize), rescale the intrinsics to that file's
size, and undistort distorted models with pycolmap into a cache (or refuse clearly).
"""

from __future__ import annotations

import copy
import hashlib
import os
from dataclasses import replace
from pathlib import Path

import numpy as np
import pycolmap
from PIL import Image

from .errors import DataError
from .images import (
    cache_file_name, derived_cache_dir, image_info, image_size, read_image, resize_to_cache, resized_size, source_stamp,
)
from .parsed import ImageRecord, ParseOptions

PINHOLE_MODELS = ("SIMPLE_PINHOLE", "PINHOLE")

UNDISTORT_HINT = (
    "undistort the dataset first (for COLMAP: `colmap image_undistorter --image_path images "
    "--input_path sparse/0 --output_path undistorted`, then use `undistorted/`), or let the loader "
    "undistort it into a cache (DataManagerConfig undistort=True, the default)"
)


def pinhole_K(camera: pycolmap.Camera) -> np.ndarray:
    """K [3, 3] float64 of a SIMPLE_PINHOLE or PINHOLE camera."""
    return np.asarray(camera.calibration_matrix(), dtype=np.float64)


def check_camera(camera: pycolmap.Camera, where: str) -> None:
    """Finite parameters, positive focal lengths and size."""
    params = np.asarray(camera.params, dtype=np.float64)
    if not np.all(np.isfinite(params)):
        raise DataError(where, f"camera parameters are not finite: {params.tolist()}")
    if camera.width < 1 or camera.height < 1:
        raise DataError(where, f"camera size {camera.width}x{camera.height} is not positive")
    focals = [params[i] for i in camera.focal_length_idxs()]
    if min(focals) <= 0:
        raise DataError(where, f"camera focal length must be positive, got {focals}")


def check_pose(viewmat: np.ndarray, where: str) -> None:
    """viewmat [4, 4]: finite, with a proper rotation (det +1, orthonormal to 1e-4)."""
    if not np.all(np.isfinite(viewmat)):
        raise DataError(where, "camera pose is not finite")
    rot = viewmat[:3, :3]
    if abs(np.linalg.det(rot) - 1.0) > 1e-4 or np.abs(rot @ rot.T - np.eye(3)).max() > 1e-4:
        raise DataError(where, "camera rotation is not orthonormal with determinant 1")


def _camera_key(camera: pycolmap.Camera) -> str:
    text = f"{camera.model_name} {camera.width} {camera.height} " + " ".join(
        f"{p:.17g}" for p in camera.params
    )
    return hashlib.sha1(text.encode()).hexdigest()[:10]


def source_image(root: Path, rel: str, factor: int, options: ParseOptions) -> Path:
    """The file to read for image ``rel`` (relative to ``root``) at ``factor``.

    factor 1: ``root/rel``. Otherwise ``root/<dir>_<factor>/<file>`` when present (the 3DGS
    ``images_4/`` convention), else a resized copy in the cache (made once per version of the
    source file; see :func:`derived_cache_dir`).
    """
    full = root / rel
    if factor == 1:
        return full
    rel_path = Path(rel)
    if rel_path.parent != Path("."):
        prescaled = root / rel_path.parent.parent / f"{rel_path.parent.name}_{factor}" / rel_path.name
        if prescaled.is_file():
            return prescaled
    width, height = image_size(full)
    cache = derived_cache_dir(root, f"resized_{factor}", options.cache_root.expanduser(), options.cache_beside_data)
    name = cache_file_name(rel, ".png", tag=f"-{source_stamp(full)}")
    return resize_to_cache(full, cache / name, resized_size(width, height, factor))


def prepare_image(
    root: Path,
    name: str,
    path: Path,
    camera: pycolmap.Camera,
    viewmat: np.ndarray,
    options: ParseOptions,
    *,
    expect_size: tuple[int, int] | None,
) -> ImageRecord:
    """An ImageRecord with a pinhole K for the file at ``path``.

    camera: the dataset's camera for the full-resolution image (any pycolmap model).
    expect_size: the (width, height) the file must have, or None to accept any size with
    the camera's aspect ratio (intrinsics are rescaled to it).
    """
    width, height, kind = image_info(path)
    if expect_size is not None and (width, height) != expect_size:
        raise DataError(path, f"image is {width}x{height} but its camera says {expect_size[0]}x{expect_size[1]}")
    cam_aspect = camera.width / camera.height
    if abs(width / height - cam_aspect) > 0.02 * cam_aspect:
        raise DataError(
            path, f"image is {width}x{height}, which does not match the camera's aspect ratio "
            f"({camera.width}x{camera.height})"
        )
    cam = copy.deepcopy(camera)
    if (width, height) != (cam.width, cam.height):
        cam.rescale(width, height)
    if cam.model_name in PINHOLE_MODELS:
        return ImageRecord(name, path, width, height, pinhole_K(cam), viewmat, pixel_kind=kind)
    if not options.undistort:
        raise DataError(path, f"camera model {cam.model_name} has lens distortion; {UNDISTORT_HINT}")
    return replace(_undistorted(root, name, path, cam, viewmat, options), pixel_kind=kind)


def _undistorted(
    root: Path, name: str, path: Path, cam: pycolmap.Camera, viewmat: np.ndarray, options: ParseOptions
) -> ImageRecord:
    """Undistort one image with pycolmap into the cache (once per camera and source file) -> pinhole record."""
    und_options = pycolmap.UndistortCameraOptions()
    try:
        pinhole = pycolmap.undistort_camera(und_options, cam)
    except Exception as err:  # pycolmap raises plain RuntimeErrors for unsupported models
        raise DataError(path, f"cannot undistort camera model {cam.model_name} ({err}); {UNDISTORT_HINT}") from err
    what = f"undistorted_f{options.data_factor}"
    cache = derived_cache_dir(root, what, options.cache_root.expanduser(), options.cache_beside_data)
    out = cache / cache_file_name(name, ".png", tag=f"-{_camera_key(cam)}-{source_stamp(path)}")
    if not out.is_file():
        pixels = read_image(path, options.background)
        bitmap, pinhole = pycolmap.undistort_image(und_options, pycolmap.Bitmap.from_array(pixels), cam)
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp = out.with_name(f".{out.name}.{os.getpid()}.tmp.png")
        Image.fromarray(np.asarray(bitmap.to_array(), dtype=np.uint8)).save(tmp)
        os.replace(tmp, out)
    return ImageRecord(name, out, pinhole.width, pinhole.height, pinhole_K(pinhole), viewmat)
