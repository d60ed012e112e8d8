"""Neu3D / DyNeRF multi-view video datasets: synchronised cameras, one clip each.

Layout (the one the Neural 3D Video release and 4DGS's preprocessing use)::

    SCENE/poses_bounds.npy          [C, 17] float: per camera, in camera-name order, a 3x5 matrix
                                    (camera-to-world rotation with columns down, right, back;
                                    the centre; then height, width, focal) and near/far bounds
    SCENE/cam00.mp4 ... camNN.mp4   one video per camera, decoded with PyAV into a cache, or
    SCENE/cam00/images/0000.png     frames already extracted (also SCENE/cam00/0000.png)
    SCENE/points3D.ply              optional initial points (x y z red green blue); else random
    SCENE/cam00/masks/0000.png      optional region labels, camNN/depths/0000.npy depths (z)

Every (camera, frame) becomes an image ``camNN/FFFF.png`` with the frame's time in [0, 1]
(frame / (frames - 1)); the test camera is ``cam00`` (the rig's centre in Neu3D), the others
train. Cameras must have the same number of frames.
"""

from __future__ import annotations

import json
import os
import re
from pathlib import Path

import numpy as np
from PIL import Image

from .camera_prep import check_pose
from .errors import DataError, dataset_folder
from .images import IMAGE_SUFFIXES, derived_cache_dir, image_size, resize_to_cache, resized_size
from .parsed import ImageRecord, ParsedScene, ParseOptions
from .transforms_json import read_ply_points

POSES_FILE = "poses_bounds.npy"
POINTS_FILE = "points3D.ply"
TEST_CAMERA = "cam00"
CAMERA_NAME = re.compile(r"^cam\d+$")
VIDEO_SUFFIXES = (".mp4", ".mov", ".avi", ".mkv")


def is_neu3d(root: Path) -> bool:
    return Path(root).is_dir() and (Path(root) / POSES_FILE).is_file()


def llff_to_viewmat(pose: np.ndarray) -> np.ndarray:
    """World-to-camera [4, 4] (OpenCV axes) from an LLFF 3x4 camera-to-world matrix whose rotation
    columns are the camera's down, right and backward axes: x = right, y = down, z = -back."""
    c2w = np.eye(4)
    c2w[:3, 0] = pose[:, 1]
    c2w[:3, 1] = pose[:, 0]
    c2w[:3, 2] = -pose[:, 2]
    c2w[:3, 3] = pose[:, 3]
    return np.linalg.inv(c2w)


def viewmat_to_llff(viewmat: np.ndarray) -> np.ndarray:
    """The inverse of :func:`llff_to_viewmat`: a 3x4 LLFF camera-to-world matrix."""
    c2w = np.linalg.inv(viewmat)
    return np.stack([c2w[:3, 1], c2w[:3, 0], -c2w[:3, 2], c2w[:3, 3]], axis=1)


def read_poses(root: Path) -> np.ndarray:
    """poses_bounds.npy as [C, 17] float64, checked."""
    path = root / POSES_FILE
    if not path.is_file():
        raise DataError(root, f"no {POSES_FILE}: a Neu3D dataset needs the cameras' poses")
    try:
        poses = np.load(path)
    except (OSError, ValueError) as err:
        raise DataError(path, f"unreadable ({err})") from err
    if poses.ndim != 2 or poses.shape[1] != 17:
        raise DataError(path, f"expected an array [cameras, 17], got shape {poses.shape}")
    if not np.all(np.isfinite(poses)):
        raise DataError(path, "holds NaN or infinite values")
    return poses.astype(np.float64)


def find_cameras(root: Path) -> list[tuple[str, Path]]:
    """(name, source) per camera in name order: a frames folder or a video file."""
    found: dict[str, Path] = {}
    for entry in sorted(root.iterdir()):
        stem = entry.name if entry.is_dir() else entry.stem
        if not CAMERA_NAME.match(stem):
            continue
        if entry.is_dir() or entry.suffix.lower() in VIDEO_SUFFIXES:
            if stem in found and found[stem].is_dir():
                continue  # extracted frames win over the video they came from
            found[stem] = entry
    if not found:
        raise DataError(root, "no cameras: expected cam00.mp4 ... or cam00/images/ ... beside poses_bounds.npy")
    return sorted(found.items(), key=lambda item: int(item[0][3:]))


def frame_files(folder: Path) -> list[Path]:
    """A camera folder's frames in name order (``images/`` inside it, else the folder itself)."""
    base = folder / "images" if (folder / "images").is_dir() else folder
    return sorted(p for p in base.iterdir() if p.is_file() and p.suffix in IMAGE_SUFFIXES)


def decode_video(video: Path, out_dir: Path, stride: int, limit: int | None, factor: int) -> list[Path]:
    """Decode ``video`` into PNG frames ``out_dir/FFFF.png`` (the source frame index), keeping
    every ``stride``-th of its first ``limit`` frames, downscaled by ``factor``. Reused while the
    video and the settings are unchanged (``out_dir/frames.json``)."""
    import av  # PyAV: FFmpeg's decoders

    stat = video.stat()
    key = {"video": str(video.resolve()), "size": stat.st_size, "mtime": stat.st_mtime_ns,
           "stride": stride, "limit": limit, "factor": factor}
    marker = out_dir / "frames.json"
    try:
        done = json.loads(marker.read_text())
        if done.get("key") == key:
            return [out_dir / name for name in done["frames"]]
    except (OSError, ValueError):
        pass
    out_dir.mkdir(parents=True, exist_ok=True)
    names: list[str] = []
    try:
        with av.open(str(video)) as container:
            if not container.streams.video:
                raise DataError(video, "has no video stream")
            for index, frame in enumerate(container.decode(video=0)):
                if limit is not None and index >= limit:
                    break
                if index % stride:
                    continue
                image = frame.to_image()
                if factor > 1:
                    image = image.resize(resized_size(*image.size, factor), Image.Resampling.BOX)
                name = f"{index:04d}.png"
                tmp = out_dir / f".{name}.{os.getpid()}.tmp.png"
                image.save(tmp)
                os.replace(tmp, out_dir / name)
                names.append(name)
    except av.error.FFmpegError as err:
        raise DataError(video, f"video is unreadable ({err})") from err
    if not names:
        raise DataError(video, "video has no frames")
    marker.write_text(json.dumps({"key": key, "frames": names}))
    return [out_dir / name for name in names]


def _camera_frames(root: Path, name: str, source: Path, options: ParseOptions) -> tuple[list[int], list[Path]]:
    """(source frame indices, image paths at the requested scale) of one camera."""
    stride, limit, factor = options.frame_stride, options.max_frames, options.data_factor
    beside = options.cache_beside_data
    if source.is_file():
        paths = decode_video(source, derived_cache_dir(root, f"frames_{factor}", options.cache_root, beside) / name,
                             stride, limit, factor)
        return [int(p.stem) for p in paths], paths
    files = frame_files(source)
    if not files:
        raise DataError(source, "camera folder holds no frames (PNG or JPEG)")
    indices = [i for i in range(len(files) if limit is None else min(limit, len(files))) if i % stride == 0]
    paths = []
    for i in indices:
        path = files[i]
        if factor > 1:
            cache = derived_cache_dir(root, f"images_{factor}", options.cache_root, beside) / name / f"{path.stem}.png"
            path = resize_to_cache(path, cache, resized_size(*image_size(path), factor))
        paths.append(path)
    return indices, paths


def read_neu3d(root: Path, options: ParseOptions) -> ParsedScene:
    """Parse a Neu3D / DyNeRF dataset (file units; normalise afterwards)."""
    root = dataset_folder(root)
    poses = read_poses(root)
    cameras = find_cameras(root)
    if len(cameras) != len(poses):
        raise DataError(root / POSES_FILE, f"has {len(poses)} poses but the folder has {len(cameras)} cameras "
                        f"({', '.join(n for n, _ in cameras)}): every camera needs its pose, in name order")
    frames = {name: _camera_frames(root, name, source, options) for name, source in cameras}
    counts = {name: len(paths) for name, (_, paths) in frames.items()}
    if len(set(counts.values())) > 1:
        listed = ", ".join(f"{name}: {count}" for name, count in counts.items())
        raise DataError(root, f"cameras have different frame counts ({listed}); the cameras of a dynamic "
                        f"scene must be synchronised (--datamanager.max-frames N keeps the first N of each)")
    span = max(max(indices) for indices, _ in frames.values())  # the clip's last used source frame
    records = []
    for (name, source), pose in zip(cameras, poses):
        mat = pose[:15].reshape(3, 5)
        height, width, focal = mat[:, 4]
        if not (height > 0 and width > 0 and focal > 0):
            raise DataError(root / POSES_FILE, f"camera {name}: height, width and focal must be > 0, got "
                            f"{height}, {width}, {focal}")
        viewmat = llff_to_viewmat(mat[:, :4])
        check_pose(viewmat, f"{root / POSES_FILE} (camera {name})")
        indices, paths = frames[name]
        img_w, img_h = image_size(paths[0])
        K = np.array([[focal * img_w / width, 0.0, img_w / 2.0],
                      [0.0, focal * img_h / height, img_h / 2.0], [0.0, 0.0, 1.0]])
        folder = source if source.is_dir() else root / name
        for index, path in zip(indices, paths):
            stem = f"{index:04d}"
            depth, mask = folder / "depths" / f"{stem}.npy", folder / "masks" / f"{stem}.png"
            records.append(ImageRecord(
                name=f"{name}/{stem}.png", path=path, width=img_w, height=img_h, K=K, viewmat=viewmat,
                depth_path=depth if depth.is_file() else None, mask_path=mask if mask.is_file() else None,
                time=index / span if span > 0 else 0.0))
    test_camera = TEST_CAMERA if TEST_CAMERA in counts else cameras[0][0]
    names = [r.name for r in records]
    test = [n for n in names if n.startswith(f"{test_camera}/")]
    split = {"train": [n for n in names if not n.startswith(f"{test_camera}/")], "test": test}
    points = rgb = None
    if (root / POINTS_FILE).is_file():
        points, rgb = read_ply_points(root / POINTS_FILE)
    return ParsedScene(name=root.name, root=root, images=records, points=points, points_rgb=rgb, split=split)
