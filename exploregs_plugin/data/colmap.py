"""COLMAP datasets through pycolmap: ``images/`` + ``sparse/0`` (binary or text).

Also read when present (the built-in scenes write them): ``depths/<stem>.npy`` (float32
camera-space z in the model's units), ``masks/<stem>.png`` (region labels) and
``split.json`` (``{"train": [...], "test": [...]}``).
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import pycolmap

from .camera_prep import check_camera, check_pose, prepare_image, source_image
from .errors import DataError, dataset_folder
from .images import IMAGE_SUFFIXES
from .parsed import ImageRecord, ParsedScene, ParseOptions

MODEL_FILES = ("cameras", "images", "points3D")


def find_sparse_dir(root: Path) -> Path:
    """``root/sparse/0`` (or ``root/sparse`` holding the model files directly)."""
    for candidate in (root / "sparse" / "0", root / "sparse"):
        if candidate.is_dir() and _model_format(candidate) is not None:
            return candidate
    if not (root / "sparse").exists():
        raise DataError(root, "no sparse/0 folder: expected a COLMAP model in sparse/0")
    raise DataError(
        root / "sparse" / "0",
        "COLMAP model is missing or empty: expected cameras, images and points3D as .bin or .txt",
    )


def _model_format(sparse: Path) -> str | None:
    for ext in ("bin", "txt"):
        if all((sparse / f"{name}.{ext}").is_file() for name in MODEL_FILES):
            return ext
    return None


def _check_text_camera_models(sparse: Path) -> None:
    """pycolmap's message for an unknown model name is obscure: name the file and the model."""
    known = set(pycolmap.CameraModelId.__members__) - {"INVALID"}
    path = sparse / "cameras.txt"
    for line_no, line in enumerate(path.read_text().splitlines(), 1):
        fields = line.split()
        if not fields or fields[0].startswith("#"):
            continue
        if len(fields) < 4 or fields[1] not in known:
            model = fields[1] if len(fields) > 1 else "?"
            raise DataError(path, f"line {line_no}: unknown camera model {model!r}")


def _data_lines(path: Path):
    """(line number, fields) of the non-comment, non-empty lines of a COLMAP text file."""
    for line_no, line in enumerate(path.read_text().splitlines(), 1):
        fields = line.split()
        if fields and not fields[0].startswith("#"):
            yield line_no, fields


def _check_text_references(sparse: Path) -> None:
    """Every camera an image (or a rig) names must be defined in cameras.txt. pycolmap's own
    message for a truncated cameras.txt is an internal check about rigs; this names the file,
    the line and the entry instead."""
    cameras_path = sparse / "cameras.txt"
    camera_ids = set()
    for line_no, fields in _data_lines(cameras_path):
        try:
            camera_ids.add(int(fields[0]))
        except ValueError:
            raise DataError(cameras_path, f"line {line_no}: camera id {fields[0]!r} is not an integer") from None
    defined = f"{cameras_path.name} defines {len(camera_ids)} camera(s)"
    images_path = sparse / "images.txt"
    # images.txt alternates a pose line (IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME) with a
    # line of 2D points, which may be empty
    lines = images_path.read_text().splitlines()
    index = 0
    for line_no, line in enumerate(lines, 1):
        if line.lstrip().startswith("#"):
            continue
        if index % 2 == 0:
            fields = line.split()
            if not fields:
                continue
            if len(fields) < 10:
                raise DataError(images_path, f"line {line_no}: expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME, "
                                             f"got {len(fields)} fields")
            if not fields[8].lstrip("-").isdigit() or int(fields[8]) not in camera_ids:
                raise DataError(images_path, f"line {line_no}: image {fields[9]!r} uses camera {fields[8]}, which "
                                             f"is not defined ({defined}; is it truncated?)")
        index += 1
    rigs_path = sparse / "rigs.txt"
    if rigs_path.is_file():
        for line_no, fields in _data_lines(rigs_path):
            # RIG_ID NUM_SENSORS REF_SENSOR_TYPE REF_SENSOR_ID [SENSOR_TYPE SENSOR_ID POSE...]
            for kind, sensor in zip(fields[2:], fields[3:]):
                if kind == "CAMERA" and sensor.isdigit() and int(sensor) not in camera_ids:
                    raise DataError(rigs_path, f"line {line_no}: rig {fields[0]} uses camera {sensor}, which is not "
                                               f"defined ({defined}; is it truncated?)")


def read_reconstruction(sparse: Path) -> pycolmap.Reconstruction:
    if _model_format(sparse) == "txt":
        _check_text_camera_models(sparse)
        _check_text_references(sparse)
    try:
        return pycolmap.Reconstruction(str(sparse))
    except Exception as err:  # pycolmap raises RuntimeError/ValueError subclasses
        raise DataError(sparse, f"cannot read the COLMAP model ({err})") from err


def _warn_unused_images(folder: Path, used: set[str]) -> None:
    """Warn, with the count, when image files in ``folder`` are not in the model (they are not
    trained on: a truncated images.txt would otherwise pass unnoticed)."""
    if not folder.is_dir():
        return
    on_disk = sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*")
                     if p.is_file() and p.suffix in IMAGE_SUFFIXES)
    unused = [name for name in on_disk if name not in used]
    if unused:
        warnings.warn(f"{folder}: {len(unused)} of {len(on_disk)} images are not in the COLMAP model and are not "
                      f"used (e.g. {', '.join(unused[:3])})", stacklevel=3)


def read_split(root: Path, names: list[str]) -> dict[str, list[str]] | None:
    """The dataset's own ``split.json`` when present, checked against ``names``."""
    path = root / "split.json"
    if not path.is_file():
        return None
    try:
        split = json.loads(path.read_text())
        train, test = list(split["train"]), list(split["test"])
    except (ValueError, KeyError, TypeError) as err:
        raise DataError(path, f"expected {{'train': [names], 'test': [names]}} ({err})") from err
    unknown = sorted(set(train + test) - set(names))
    if unknown:
        raise DataError(path, f"names not in the dataset: {unknown[:5]}")
    return {"train": train, "test": test}


def attach_extras(root: Path, record: ImageRecord) -> ImageRecord:
    """Set depth/mask paths when ``depths/<stem>.npy`` / ``masks/<stem>.png`` exist."""
    stem = Path(record.name).stem
    depth, mask = root / "depths" / f"{stem}.npy", root / "masks" / f"{stem}.png"
    record.depth_path = depth if depth.is_file() else None
    record.mask_path = mask if mask.is_file() else None
    return record


def read_colmap(root: Path, options: ParseOptions) -> ParsedScene:
    """Parse a COLMAP dataset (file units; normalise afterwards)."""
    root = dataset_folder(root)
    sparse = find_sparse_dir(root)
    rec = read_reconstruction(sparse)
    images = sorted(rec.images.values(), key=lambda im: im.name)
    if not images:
        raise DataError(sparse, "the COLMAP model has zero images")
    records = []
    for im in images:
        where = f"{sparse} (image {im.name!r})"
        camera = rec.cameras[im.camera_id]
        check_camera(camera, where)
        if not im.has_pose:
            raise DataError(where, "image has no pose (not registered)")
        viewmat = np.eye(4)
        viewmat[:3, :] = np.asarray(im.cam_from_world().matrix(), dtype=np.float64)
        check_pose(viewmat, where)
        path = source_image(root, f"images/{im.name}", options.data_factor, options)
        expect = (camera.width, camera.height) if options.data_factor == 1 else None
        record = prepare_image(root, im.name, path, camera, viewmat, options, expect_size=expect)
        records.append(attach_extras(root, record))
    _warn_unused_images(root / "images", {im.name for im in images})
    points, rgb = _points(rec)
    if points is None:
        warnings.warn(f"{sparse}: the COLMAP model has no 3D points; using random initialisation",
                      stacklevel=2)
    return ParsedScene(
        name=root.name,
        root=root,
        images=records,
        points=points,
        points_rgb=rgb,
        split=read_split(root, [r.name for r in records]),
    )


def _points(rec: pycolmap.Reconstruction) -> tuple[np.ndarray | None, np.ndarray | None]:
    if rec.num_points3D() == 0:
        return None, None
    ids = sorted(rec.points3D.keys())
    xyz = np.array([rec.points3D[i].xyz for i in ids], dtype=np.float64)
    rgb = np.array([rec.points3D[i].color for i in ids], dtype=np.float64) / 255.0
    finite = np.all(np.isfinite(xyz), axis=1)
    if not finite.all():
        warnings.warn(f"dropping {int((~finite).sum())} non-finite COLMAP points", stacklevel=3)
    return xyz[finite], rgb[finite]
