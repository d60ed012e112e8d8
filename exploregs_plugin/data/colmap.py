"""COLMAP datasets through pycolmap: ``images/`` + ``sparse/0`` (binary or text).

Also read when present (the built-in scenes write them): ``depths/<stem>.npy`` (float32
camera-space z in the model's units), ``masks/<stem>.png`` (region labels) and
``split.json`` (``{"train": [...], "test": [...]}``).
"""

from __future__ import annotations

import functools
import json
import math
import struct
import warnings
from pathlib import Path

import numpy as np
import pycolmap

from .camera_prep import check_camera, check_pose, prepare_image, source_image
from .errors import DataError, dataset_folder
from .images import IMAGE_SUFFIXES
from .parsed import ImageRecord, ParsedScene, ParseOptions
from .process.checks import folded_warning

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


class _Truncated(Exception):
    """A binary model file ends inside a record."""


class _BinaryReader:
    """Walks a COLMAP ``.bin`` file record by record (little-endian), to say where it breaks."""

    def __init__(self, data: bytes) -> None:
        self.data, self.pos = data, 0

    def take(self, layout: struct.Struct) -> tuple:
        if self.pos + layout.size > len(self.data):
            raise _Truncated
        values = layout.unpack_from(self.data, self.pos)
        self.pos += layout.size
        return values

    def skip(self, count: int, record_size: int) -> None:
        if self.pos + count * record_size > len(self.data):
            raise _Truncated
        self.pos += count * record_size

    def name(self) -> None:
        end = self.data.find(b"\0", self.pos)
        if end < 0:
            raise _Truncated
        self.pos = end + 1


_COUNT, _CAMERA, _IMAGE, _POINT = (struct.Struct(f) for f in ("<Q", "<IiQQ", "<I7dI", "<Q3d3BdQ"))


@functools.lru_cache(maxsize=None)
def _camera_param_count(model_id: int) -> int | None:
    try:
        model = pycolmap.CameraModelId(model_id)
        return len(pycolmap.Camera.create_from_model_id(0, model, 1.0, 1, 1).params) if model_id >= 0 else None
    except (ValueError, TypeError, RuntimeError):
        return None


def _binary_problem(path: Path) -> str | None:
    """What is wrong with binary model file ``path`` (cameras, images or points3D), or None when
    every record it announces is complete and nothing follows them."""
    data = path.read_bytes()
    reader, kind = _BinaryReader(data), path.stem
    what = {"cameras": "camera", "images": "image", "points3D": "point"}[kind]
    try:
        (count,) = reader.take(_COUNT)
    except _Truncated:
        return f"truncated: {len(data)} bytes, too short for the record count"
    index = 0
    try:
        for index in range(count):
            if kind == "cameras":
                _camera_id, model_id, _width, _height = reader.take(_CAMERA)
                n_params = _camera_param_count(model_id)
                if n_params is None:
                    return f"camera {index + 1} of {count} has unknown camera model id {model_id}"
                reader.skip(n_params, 8)
            elif kind == "images":
                reader.take(_IMAGE)
                reader.name()
                (n_points2d,) = reader.take(_COUNT)
                reader.skip(n_points2d, 24)
            else:
                *_point, track_length = reader.take(_POINT)
                reader.skip(track_length, 8)
    except _Truncated:
        return (f"truncated: the file ({len(data)} bytes) ends inside {what} {index + 1} of the {count} "
                f"its header announces")
    if reader.pos != len(data):
        return f"{len(data) - reader.pos} bytes follow the last of its {count} {what}s (a corrupt file?)"
    return None


def _text_problem(path: Path) -> str | None:
    """The first line of text model file ``path`` with a value pycolmap cannot take (not a
    number, or a non-finite number), or None."""
    kind = path.stem
    if kind == "images":  # a pose line, then a line of 2D points (X Y POINT3D_ID ...), maybe empty
        lines = [(n, line.split()) for n, line in enumerate(path.read_text().splitlines(), 1)
                 if not line.lstrip().startswith("#")]
        entries = [(n, fields, f"image {lines[i - 1][1][-1] if i % 2 else fields[-1]!r}",
                    fields if i % 2 else fields[1:8]) for i, (n, fields) in enumerate(lines) if fields]
    elif kind == "cameras":
        entries = [(n, fields, f"camera {fields[0]}", fields[2:]) for n, fields in _data_lines(path)]
    else:
        entries = [(n, fields, f"point {fields[0]}", fields[1:]) for n, fields in _data_lines(path)]
    for line_no, fields, entry, numbers in entries:
        if kind == "points3D" and len(fields) < 8:
            return f"line {line_no}: expected POINT3D_ID X Y Z R G B ERROR TRACK[], got {len(fields)} fields"
        for value in numbers:
            try:
                number = float(value)
            except ValueError:
                return f"line {line_no} ({entry}): {value!r} is not a number"
            if not math.isfinite(number):
                return f"line {line_no} ({entry}): {value!r} is not a finite number"
    return None


def _text_problem_in(sparse: Path) -> tuple[Path, str] | None:
    """(file, what is wrong) for the first text model file with a value pycolmap cannot take."""
    for name in MODEL_FILES:
        problem = _text_problem(sparse / f"{name}.txt")
        if problem is not None:
            return sparse / f"{name}.txt", problem
    return None


def read_reconstruction(sparse: Path) -> pycolmap.Reconstruction:
    if _model_format(sparse) == "txt":
        _check_text_camera_models(sparse)
        _check_text_references(sparse)
    else:
        # walked before pycolmap reads them: on a truncated file pycolmap takes garbage for a
        # count and can allocate gigabytes before it fails (0.1 s per 100k points)
        for name in MODEL_FILES:
            problem = _binary_problem(sparse / f"{name}.bin")
            if problem is not None:
                raise DataError(sparse / f"{name}.bin", problem)
    try:
        return pycolmap.Reconstruction(str(sparse))
    except Exception as err:  # pycolmap raises RuntimeError/ValueError/MemoryError subclasses
        # pycolmap's own message is an internal check of its reader: find the text file and line
        # that it could not take (only on failure, so a good model is read once)
        broken = _text_problem_in(sparse) if _model_format(sparse) == "txt" else None
        if broken is not None:
            raise DataError(broken[0], broken[1]) from err
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
    folded = folded_warning(rec, sparse)
    if folded:
        warnings.warn(folded, stacklevel=2)
    points, rgb = _points(rec, sparse)
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


def _points(rec: pycolmap.Reconstruction, sparse: Path) -> tuple[np.ndarray | None, np.ndarray | None]:
    if rec.num_points3D() == 0:
        return None, None
    ids = sorted(rec.points3D.keys())
    xyz = np.array([rec.points3D[i].xyz for i in ids], dtype=np.float64)
    rgb = np.array([rec.points3D[i].color for i in ids], dtype=np.float64) / 255.0
    finite = np.all(np.isfinite(xyz), axis=1)
    if not finite.all():
        where = sparse / f"points3D.{_model_format(sparse)}"
        warnings.warn(f"{where}: left out {int((~finite).sum())} of {len(xyz)} points with non-finite "
                      f"coordinates", stacklevel=3)
    return xyz[finite], rgb[finite]
