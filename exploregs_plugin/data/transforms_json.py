"""NeRF-style ``transforms.json`` datasets (Blender / NeRF-synthetic, instant-ngp, nerfstudio).

Read:
* intrinsics from ``fl_x, fl_y, cx, cy, w, h`` or ``camera_angle_x`` (+ ``camera_angle_y``),
  top level or per frame (a frame's keys override the top level); missing ``w``/``h`` come
  from the image file; intrinsics given for another resolution than the files are rescaled;
* distortion ``k1 k2 (k3 k4) p1 p2`` (OPENCV / FULL_OPENCV, or ``camera_model:
  OPENCV_FISHEYE`` with ``k1..k4``): undistorted with pycolmap into a cache, or refused;
* ``transform_matrix``: camera-to-world in OpenGL axes (x right, y up, z back), turned into
  OpenCV axes by negating the camera y and z columns: ``c2w_cv = c2w_gl @ diag(1, -1, -1, 1)``;
* RGBA images composited over the configured background (a Blender folder's default: white);
* ``ply_file_path`` points (x y z, red green blue), else random points (the datamanager's);
* splits: ``train_filenames``/``test_filenames`` (nerfstudio), or a folder of
  ``transforms_train.json`` with ``transforms_test.json`` or ``transforms_val.json`` as the
  evaluated split (Blender / NeRF-synthetic, D-NeRF; ``ParseOptions.eval_split``);
* a frame's ``time`` in [0, 1] (D-NeRF: a monocular video, one pose per moment): every frame
  of the dataset has one, or none has.

Write: :func:`write_transforms` exports a parsed scene (file units, OpenGL axes, per-frame
pinhole intrinsics, points as PLY) that this reader loads back to the same cameras.
"""

from __future__ import annotations

import json
import math
import os
import warnings
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import pycolmap

from .backgrounds import NAMED, default_background
from .camera_prep import check_camera, check_pose, prepare_image, source_image
from .colmap import attach_extras
from .errors import DataError
from .images import IMAGE_SUFFIXES, image_size
from .parsed import BLENDER_LAYOUT, ParsedScene, ParseOptions

GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])
"""Right-multiplying a camera-to-world matrix by this flips camera y and z (OpenGL <-> OpenCV)."""

INTRINSIC_KEYS = ("fl_x", "fl_y", "cx", "cy", "w", "h", "camera_angle_x", "camera_angle_y",
                  "k1", "k2", "k3", "k4", "p1", "p2", "camera_model")


def _load_json(path: Path) -> dict[str, Any]:
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError as err:
        raise DataError(path, "file does not exist") from err
    except (ValueError, OSError) as err:
        raise DataError(path, f"not valid JSON ({err})") from err
    if not isinstance(data, dict):
        raise DataError(path, "expected a JSON object at the top level")
    if "frames" not in data:
        raise DataError(path, "missing required key 'frames'")
    if not isinstance(data["frames"], list):
        raise DataError(path, "'frames' must be a list")
    return data


def _resolve_image(base: Path, file_path: str, where: str) -> str:
    """The image path relative to ``base``: ``file_path`` itself, or (Blender omits the
    extension) ``file_path`` plus one of the usual image suffixes. DataError when neither exists."""
    rel = Path(file_path)
    if (base / rel).is_file():
        return os.path.normpath(rel.as_posix())
    # Appended, not with_suffix: "r_0.5" or "frame.001" keep their dots.
    for suffix in IMAGE_SUFFIXES:
        if (base / f"{rel.as_posix()}{suffix}").is_file():
            return os.path.normpath(f"{rel.as_posix()}{suffix}")
    tried = "" if rel.suffix.lower() in IMAGE_SUFFIXES else " nor with .png (or .jpg)"
    raise DataError(where, f"file_path {file_path!r} names no image: {base / rel} does not exist{tried}")


def _frame_camera(meta: dict[str, Any], frame: dict[str, Any], image_path: Path, where: str) -> pycolmap.Camera:
    """A pycolmap camera for one frame, from top-level keys overridden by the frame's."""
    merged = {k: meta[k] for k in INTRINSIC_KEYS if k in meta}
    merged.update({k: frame[k] for k in INTRINSIC_KEYS if k in frame})
    if "w" in merged and "h" in merged:
        width, height = float(merged["w"]), float(merged["h"])
    else:
        width, height = (float(v) for v in image_size(image_path))
    if "fl_x" in merged or "fl_y" in merged:
        fx = float(merged.get("fl_x", merged.get("fl_y")))
        fy = float(merged.get("fl_y", fx))
    elif "camera_angle_x" in merged:
        angle = float(merged["camera_angle_x"])
        if not 0.0 < angle < math.pi:
            raise DataError(where, f"camera_angle_x must be in (0, pi), got {angle}")
        fx = 0.5 * width / math.tan(0.5 * angle)
        angle_y = merged.get("camera_angle_y")
        fy = 0.5 * height / math.tan(0.5 * float(angle_y)) if angle_y is not None and 0 < float(angle_y) < math.pi else fx
    else:
        raise DataError(where, "missing intrinsics: need 'fl_x' (and 'fl_y') or 'camera_angle_x'")
    cx = float(merged.get("cx", width / 2))
    cy = float(merged.get("cy", height / 2))
    k = [float(merged.get(f"k{i}", 0.0)) for i in range(1, 5)]
    p = [float(merged.get("p1", 0.0)), float(merged.get("p2", 0.0))]
    model = str(merged.get("camera_model", "OPENCV")).upper()
    if width != round(width) or height != round(height):
        raise DataError(where, f"image size w={width}, h={height} must be whole numbers")
    if model == "OPENCV_FISHEYE":
        name, params = "OPENCV_FISHEYE", [fx, fy, cx, cy, *k]
    elif model not in ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE"):
        raise DataError(where, f"unknown camera_model {model!r}; expected OPENCV or OPENCV_FISHEYE")
    elif k[2] != 0.0 or k[3] != 0.0:
        name, params = "FULL_OPENCV", [fx, fy, cx, cy, k[0], k[1], *p, k[2], k[3], 0.0, 0.0]
    elif any(v != 0.0 for v in (*k, *p)):
        name, params = "OPENCV", [fx, fy, cx, cy, k[0], k[1], *p]
    else:
        name, params = "PINHOLE", [fx, fy, cx, cy]
    camera = pycolmap.Camera(model=name, width=int(width), height=int(height), params=params)
    check_camera(camera, where)
    return camera


def _frame_viewmat(frame: dict[str, Any], where: str) -> np.ndarray:
    if "transform_matrix" not in frame:
        raise DataError(where, "missing required key 'transform_matrix'")
    try:
        c2w = np.asarray(frame["transform_matrix"], dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise DataError(where, f"transform_matrix is not a numeric matrix ({err})") from err
    if c2w.shape == (3, 4):
        c2w = np.concatenate([c2w, [[0.0, 0.0, 0.0, 1.0]]], axis=0)
    if c2w.shape != (4, 4):
        raise DataError(where, f"transform_matrix must be 4x4 (or 3x4), got shape {c2w.shape}")
    if not np.all(np.isfinite(c2w)):
        raise DataError(where, "camera pose is not finite")
    c2w_cv = c2w @ GL_TO_CV
    viewmat = np.eye(4)
    rot = c2w_cv[:3, :3]
    viewmat[:3, :3] = rot.T
    viewmat[:3, 3] = -rot.T @ c2w_cv[:3, 3]
    check_pose(viewmat, where)
    return viewmat


def read_ply_points(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """xyz [P, 3] float64 and rgb [P, 3] in [0, 1] (0.5 grey without colours) from a PLY."""
    from plyfile import PlyData  # local: only transforms.json datasets need it

    try:
        ply = PlyData.read(str(path))
        vertex = ply["vertex"]
        xyz = np.stack([vertex["x"], vertex["y"], vertex["z"]], axis=1).astype(np.float64)
    except FileNotFoundError as err:
        raise DataError(path, "point cloud file (ply_file_path) does not exist") from err
    except (KeyError, ValueError, OSError) as err:
        raise DataError(path, f"cannot read vertices x, y, z ({err})") from err
    names = vertex.data.dtype.names or ()
    if all(c in names for c in ("red", "green", "blue")):
        rgb = np.stack([vertex["red"], vertex["green"], vertex["blue"]], axis=1).astype(np.float64) / 255.0
    else:
        rgb = np.full_like(xyz, 0.5)
    finite = np.all(np.isfinite(xyz), axis=1)
    return xyz[finite], rgb[finite]


def write_ply_points(path: Path, xyz: np.ndarray, rgb: np.ndarray) -> None:
    """xyz [P, 3], rgb [P, 3] in [0, 1] -> binary PLY with float64 positions, uint8 colours."""
    from plyfile import PlyData, PlyElement

    data = np.empty(len(xyz), dtype=[("x", "f8"), ("y", "f8"), ("z", "f8"),
                                     ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    data["x"], data["y"], data["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    colors = np.clip(np.round(rgb * 255.0), 0, 255).astype(np.uint8)
    data["red"], data["green"], data["blue"] = colors[:, 0], colors[:, 1], colors[:, 2]
    PlyData([PlyElement.describe(data, "vertex")]).write(str(path))


@dataclass(frozen=True)
class _Frame:
    """One frame and where it came from: ``where`` names the json file and the frame's index in
    it; ``entry`` is the frame with its file's top-level intrinsics filled in."""

    where: str
    entry: dict[str, Any]


def _frames_and_split(path: Path, eval_split: str) -> tuple[Path, dict[str, Any], list[_Frame], dict[str, list[str]] | None]:
    """(json path for messages, top-level meta, frames, split by file path or None).

    A Blender folder contributes ``transforms_train.json`` (training) and
    ``transforms_{eval_split}.json`` (the evaluated split, under the key "test"); both must exist."""
    if path.is_dir():
        parts = {"train": path / "transforms_train.json", "test": path / f"transforms_{eval_split}.json"}
        for key, part in parts.items():
            if not part.is_file():
                use = "training" if key == "train" else f"evaluation (--datamanager.eval-split {eval_split})"
                raise DataError(part, f"split file does not exist; a Blender folder needs it for {use}")
        metas = {key: _load_json(part) for key, part in parts.items()}
        frames, split = [], {"train": [], "test": []}
        for key, meta in metas.items():
            for index, frame in enumerate(meta["frames"]):
                entry = {**{k: meta[k] for k in INTRINSIC_KEYS if k in meta}, **frame} if isinstance(frame, dict) else frame
                frames.append(_Frame(f"{parts[key]} (frame {index})", entry))
                split[key].append(str(frame.get("file_path", "")) if isinstance(frame, dict) else "")
        return parts["train"], metas["train"], frames, split
    meta = _load_json(path)
    split = None
    if "train_filenames" in meta or "test_filenames" in meta:
        split = {"train": list(meta.get("train_filenames", [])), "test": list(meta.get("test_filenames", []))}
    return path, meta, [_Frame(f"{path} (frame {i})", f) for i, f in enumerate(meta["frames"])], split


def _frame_times(frames: list[_Frame]) -> list[float | None]:
    """Each frame's ``time`` (all None when no frame has one). DataError, naming the frame's
    file, when some frames have a time and this one has none, or a time outside [0, 1]."""
    timed = [f for f in frames if isinstance(f.entry, dict) and "time" in f.entry]
    if not timed:
        return [None] * len(frames)
    times = []
    for frame in frames:
        if not isinstance(frame.entry, dict) or "time" not in frame.entry:
            raise DataError(frame.where, f"has no 'time', though other frames have one ({timed[0].where}): "
                            "a dynamic (D-NeRF) dataset needs the time of every frame")
        try:
            time = float(frame.entry["time"])
        except (TypeError, ValueError) as err:
            raise DataError(frame.where, f"'time' must be a number in [0, 1], got {frame.entry['time']!r}") from err
        if not 0.0 <= time <= 1.0:  # also refuses NaN
            raise DataError(frame.where, f"'time' must be in [0, 1] (0 = first moment, 1 = last), got {time}")
        times.append(time)
    return times


def read_transforms(path: Path, options: ParseOptions) -> ParsedScene:
    """Parse a transforms.json file (or a Blender folder of transforms_{train,val,test}.json)."""
    path = Path(path)
    json_path, meta, frames, split = _frames_and_split(path, options.eval_split)
    base = json_path.parent
    if not frames:
        raise DataError(json_path, "'frames' is empty: zero images")
    layout = BLENDER_LAYOUT if path.is_dir() else None
    if options.background is None:  # the layout's convention (white for Blender, else black)
        options = replace(options, background=np.asarray(NAMED[default_background(layout)], dtype=np.float64))
    times = _frame_times(frames)
    records, by_file, first_size = [], {}, None
    for frame, time in zip(frames, times):
        where, entry = frame.where, frame.entry
        if not isinstance(entry, dict) or "file_path" not in entry:
            raise DataError(where, "missing required key 'file_path'")
        rel = _resolve_image(base, str(entry["file_path"]), where)
        viewmat = _frame_viewmat(entry, where)
        full = base / rel
        if layout == BLENDER_LAYOUT:
            # One camera_angle_x serves every frame of a Blender folder: one image size.
            size = image_size(full)
            first_size = first_size or (size, full)
            if size != first_size[0]:
                raise DataError(full, f"image is {size[0]}x{size[1]} but {first_size[1]} is "
                                f"{first_size[0][0]}x{first_size[0][1]}: the frames of a Blender dataset "
                                "share one camera, so their images must have one size")
        camera = _frame_camera(meta, entry, full, where)
        src = source_image(base, rel, options.data_factor, options)
        record = prepare_image(base, rel, src, camera, viewmat, options, expect_size=None)
        records.append(replace(attach_extras(base, record), time=time))
        by_file[os.path.normpath(str(entry["file_path"]))] = rel
    names = [r.name for r in records]
    if len(set(names)) != len(names):
        raise DataError(json_path, "two frames use the same image file")
    order = np.argsort(names, kind="stable")
    records = [records[i] for i in order]
    points, rgb = None, None
    if "ply_file_path" in meta:
        points, rgb = read_ply_points(base / str(meta["ply_file_path"]))
        if len(points) == 0:
            warnings.warn(f"{base / str(meta['ply_file_path'])}: empty point cloud; using random "
                          "initialisation", stacklevel=2)
            points, rgb = None, None
    return ParsedScene(
        name=base.name,
        root=base,
        images=records,
        points=points,
        points_rgb=rgb,
        split=_map_split(split, by_file, json_path),
        background=options.background,
        layout=layout,
    )


def _map_split(split: dict[str, list[str]] | None, by_file: dict[str, str], where: Path) -> dict[str, list[str]] | None:
    if split is None:
        return None
    out: dict[str, list[str]] = {}
    for key, files in split.items():
        names = []
        for f in files:
            norm = os.path.normpath(f)
            if norm in by_file:
                names.append(by_file[norm])
            elif norm in by_file.values():
                names.append(norm)
            else:
                raise DataError(where, f"{key}_filenames lists {f!r}, which is not a frame")
        out[key] = names
    return out


def write_transforms(scene: ParsedScene, out_path: Path, write_points: bool = True) -> Path:
    """Export ``scene`` as a transforms.json at ``out_path`` (in the scene's file units).

    Per-frame pinhole intrinsics, OpenGL camera-to-world poses, image paths relative to the
    json's folder, each frame's time in a dynamic scene, points (if any) as ``points3D.ply``
    beside it, and the split if known.
    """
    out_path = Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    norm = scene.normalization
    frames = []
    for im in scene.images:
        w2c = norm.invert_viewmat(im.viewmat)
        c2w = np.linalg.inv(w2c) @ GL_TO_CV
        frames.append({
            "file_path": os.path.relpath(im.path, out_path.parent),
            "transform_matrix": c2w.tolist(),
            "fl_x": float(im.K[0, 0]), "fl_y": float(im.K[1, 1]),
            "cx": float(im.K[0, 2]), "cy": float(im.K[1, 2]),
            "w": int(im.width), "h": int(im.height),
            **({} if im.time is None else {"time": float(im.time)}),
        })
    meta: dict[str, Any] = {"frames": frames}
    if scene.points is not None and write_points:
        write_ply_points(out_path.parent / "points3D.ply", norm.invert_points(scene.points), scene.points_rgb)
        meta["ply_file_path"] = "points3D.ply"
    if scene.split is not None:
        path_of = {im.name: os.path.relpath(im.path, out_path.parent) for im in scene.images}
        meta["train_filenames"] = [path_of[n] for n in scene.split["train"]]
        meta["test_filenames"] = [path_of[n] for n in scene.split["test"]]
    out_path.write_text(json.dumps(meta, indent=1))
    return out_path
