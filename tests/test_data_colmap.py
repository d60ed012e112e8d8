"""COLMAP parsing: binary vs text, distortion, --data-factor, caches, and every bad input."""

from __future__ import annotations

import os
import shutil
import stat
from pathlib import Path

import numpy as np
import pycolmap
import pytest
from PIL import Image

from exploregs_plugin.data import DataError, ParseOptions, read_colmap


@pytest.fixture()
def scene_copy(tiny_scene_dir: Path, tmp_path: Path) -> Path:
    """A private, writable copy of the tiny scene."""
    return Path(shutil.copytree(tiny_scene_dir, tmp_path / "scene"))


def _same_scene(a, b) -> None:
    assert [im.name for im in a.images] == [im.name for im in b.images]
    for x, y in zip(a.images, b.images):
        np.testing.assert_array_equal(x.K, y.K)
        np.testing.assert_allclose(x.viewmat, y.viewmat, rtol=0, atol=1e-15)
        assert (x.width, x.height, x.path) == (y.width, y.height, y.path)
    np.testing.assert_array_equal(a.points, b.points)
    np.testing.assert_array_equal(a.points_rgb, b.points_rgb)


def _rewrite_model(root: Path, edit, binary: bool = False) -> None:
    sparse = root / "sparse" / "0"
    rec = pycolmap.Reconstruction(str(sparse))
    edit(rec)
    for f in sparse.iterdir():
        f.unlink()
    (rec.write_binary if binary else rec.write_text)(str(sparse))


def test_binary_and_text_models_give_identical_results(scene_copy: Path, tmp_path: Path) -> None:
    text = read_colmap(scene_copy, ParseOptions())
    _rewrite_model(scene_copy, lambda rec: None, binary=True)
    assert (scene_copy / "sparse" / "0" / "images.bin").is_file()
    binary = read_colmap(scene_copy, ParseOptions())
    _same_scene(text, binary)


def test_model_directly_in_sparse_folder(scene_copy: Path) -> None:
    for f in (scene_copy / "sparse" / "0").iterdir():
        f.rename(scene_copy / "sparse" / f.name)
    (scene_copy / "sparse" / "0").rmdir()
    assert len(read_colmap(scene_copy, ParseOptions()).images) == 10


def _simple_radial(k1: float):
    """A model edit: every camera becomes SIMPLE_RADIAL with distortion ``k1``."""
    def edit(rec: pycolmap.Reconstruction) -> None:
        for cam in rec.cameras.values():
            fx, _fy, cx, cy = cam.params
            cam.model = pycolmap.CameraModelId.SIMPLE_RADIAL
            cam.params = [fx, cx, cy, k1]

    return edit


def test_distorted_model_is_refused_or_undistorted_into_a_cache(scene_copy: Path, tmp_path: Path) -> None:
    _rewrite_model(scene_copy, _simple_radial(0.08))
    with pytest.raises(DataError, match="SIMPLE_RADIAL has lens distortion.*image_undistorter"):
        read_colmap(scene_copy, ParseOptions(undistort=False))
    cache = tmp_path / "cache"
    scene = read_colmap(scene_copy, ParseOptions(undistort=True, cache_root=cache))
    im = scene.images[0]
    assert im.path.parent.name == "undistorted_f1" and cache / "derived" in im.path.parents
    assert not (scene_copy / ".exploregs").exists()  # the dataset folder is never written to
    with Image.open(im.path) as pic:
        assert pic.size == (im.width, im.height)
    assert im.K[0, 1] == 0 and im.K[0, 0] > 0 and im.K[1, 1] > 0
    assert 0 < im.width <= 2 * 64 and 0 < im.height <= 2 * 48
    stamp = im.path.stat().st_mtime_ns
    again = read_colmap(scene_copy, ParseOptions(undistort=True, cache_root=cache))
    assert again.images[0].path == im.path and im.path.stat().st_mtime_ns == stamp
    np.testing.assert_array_equal(again.images[0].K, im.K)
    # a changed source image is undistorted again, never served stale from the cache
    source = scene_copy / "images" / im.name
    Image.new("RGB", (64, 48), (200, 10, 10)).save(source)
    changed = read_colmap(scene_copy, ParseOptions(undistort=True, cache_root=cache)).images[0]
    assert changed.path != im.path and changed.path.is_file()
    with Image.open(changed.path) as pic:
        assert np.asarray(pic)[im.height // 2, im.width // 2, 0] == 200


def test_data_factor_resizes_once_and_scales_K(scene_copy: Path) -> None:
    full = read_colmap(scene_copy, ParseOptions())
    half = read_colmap(scene_copy, ParseOptions(data_factor=2))
    im, im2 = full.images[1], half.images[1]
    assert (im2.width, im2.height) == (32, 24)
    assert im2.path.parent.parent.name == "resized_2" and im2.path.name.startswith(Path(im.name).stem + "-")
    np.testing.assert_allclose(im2.K[:2], im.K[:2] * 0.5)
    stamp = im2.path.stat().st_mtime_ns
    read_colmap(scene_copy, ParseOptions(data_factor=2))
    assert im2.path.stat().st_mtime_ns == stamp


def test_caches_beside_the_data_only_when_asked(scene_copy: Path, tmp_path: Path) -> None:
    cache = tmp_path / "cache"
    elsewhere = read_colmap(scene_copy, ParseOptions(data_factor=2, cache_root=cache)).images[1]
    assert cache / "derived" in elsewhere.path.parents and not (scene_copy / ".exploregs").exists()
    beside = read_colmap(scene_copy, ParseOptions(data_factor=2, cache_root=cache, cache_beside_data=True)).images[1]
    assert beside.path.parent == scene_copy / ".exploregs" / "resized_2" / "images"
    # another copy of the same dataset has its own cache folder (keyed by the absolute path)
    other = Path(shutil.copytree(scene_copy / "images", tmp_path / "other" / "images")).parent
    shutil.copytree(scene_copy / "sparse", other / "sparse")
    assert read_colmap(other, ParseOptions(data_factor=2, cache_root=cache)).images[1].path.parents[2] != \
        elsewhere.path.parents[2]


def test_data_factor_prefers_images_n_folder(scene_copy: Path) -> None:
    (scene_copy / "images_4").mkdir()
    for f in (scene_copy / "images").iterdir():
        Image.open(f).resize((16, 12)).save(scene_copy / "images_4" / f.name)
    scene = read_colmap(scene_copy, ParseOptions(data_factor=4))
    assert scene.images[0].path.parent == scene_copy / "images_4"
    assert (scene.images[0].width, scene.images[0].height) == (16, 12)
    assert not (scene_copy / ".exploregs").exists()


def test_read_only_dataset_caches_under_the_cache_root(scene_copy: Path, tmp_path: Path) -> None:
    cache = tmp_path / "cache"
    os.chmod(scene_copy, stat.S_IRUSR | stat.S_IXUSR | stat.S_IRGRP | stat.S_IXGRP)
    try:
        scene = read_colmap(scene_copy, ParseOptions(data_factor=2, cache_root=cache))
    finally:
        os.chmod(scene_copy, stat.S_IRWXU)
    assert cache in scene.images[0].path.parents
    assert not (scene_copy / ".exploregs").exists()


# ---- bad input: each gets a clear error naming the file and the problem ----

def test_missing_image_file(scene_copy: Path) -> None:
    (scene_copy / "images" / "0003.png").unlink()
    with pytest.raises(DataError, match=r"0003\.png: image file is missing"):
        read_colmap(scene_copy, ParseOptions())


def test_image_size_disagrees_with_camera(scene_copy: Path) -> None:
    Image.new("RGB", (50, 40)).save(scene_copy / "images" / "0002.png")
    with pytest.raises(DataError, match=r"0002\.png: image is 50x40 but its camera says 64x48"):
        read_colmap(scene_copy, ParseOptions())


def test_unreadable_image(scene_copy: Path) -> None:
    (scene_copy / "images" / "0005.png").write_bytes(b"not a png at all")
    with pytest.raises(DataError, match=r"0005\.png: image file is unreadable"):
        read_colmap(scene_copy, ParseOptions())


def test_missing_sparse_folder(scene_copy: Path) -> None:
    shutil.rmtree(scene_copy / "sparse")
    with pytest.raises(DataError, match="no sparse/0"):
        read_colmap(scene_copy, ParseOptions())


def test_empty_sparse_folder(scene_copy: Path) -> None:
    for f in (scene_copy / "sparse" / "0").iterdir():
        f.unlink()
    with pytest.raises(DataError, match=r"sparse/0: COLMAP model is missing or empty"):
        read_colmap(scene_copy, ParseOptions())


def test_unknown_camera_model(scene_copy: Path) -> None:
    path = scene_copy / "sparse" / "0" / "cameras.txt"
    lines = path.read_text().splitlines()
    lines = [ln.replace(" PINHOLE ", " FOOBAR ", 1) if ln.startswith("3 ") else ln for ln in lines]
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(DataError, match=r"cameras\.txt: line \d+: unknown camera model 'FOOBAR'"):
        read_colmap(scene_copy, ParseOptions())


def test_non_finite_pose(scene_copy: Path) -> None:
    def break_pose(rec: pycolmap.Reconstruction) -> None:
        frame = rec.frames[rec.images[3].frame_id]
        pose = frame.rig_from_world
        frame.rig_from_world = pycolmap.Rigid3d(pose.rotation, np.array([np.nan, 0.0, 0.0]))

    _rewrite_model(scene_copy, break_pose, binary=True)
    with pytest.raises(DataError, match=r"image '0002\.png'.*camera pose is not finite"):
        read_colmap(scene_copy, ParseOptions())


def test_zero_images(scene_copy: Path) -> None:
    sparse = scene_copy / "sparse" / "0"
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(pycolmap.Camera(model="PINHOLE", width=64, height=48,
                                                    params=[50, 50, 32, 24], camera_id=1))
    for f in sparse.iterdir():
        f.unlink()
    rec.write_text(str(sparse))
    with pytest.raises(DataError, match="zero images"):
        read_colmap(scene_copy, ParseOptions())


def test_empty_point_cloud_falls_back_to_random_init(scene_copy: Path) -> None:
    _rewrite_model(scene_copy, lambda rec: [rec.delete_point3D(i) for i in list(rec.point3D_ids())])
    with pytest.warns(UserWarning, match="no 3D points; using random initialisation"):
        scene = read_colmap(scene_copy, ParseOptions())
    assert scene.points is None and scene.points_rgb is None  # the datamanager initialises


def test_dataset_folder_missing(tmp_path: Path) -> None:
    with pytest.raises(DataError, match="dataset folder does not exist"):
        read_colmap(tmp_path / "nothing", ParseOptions())


def test_truncated_cameras_txt_names_the_image_and_camera(scene_copy: Path) -> None:
    path = scene_copy / "sparse" / "0" / "cameras.txt"
    lines = path.read_text().splitlines()
    data = [ln for ln in lines if ln and not ln.startswith("#")]
    assert len(data) == 10
    kept = [ln for ln in lines if ln.startswith("#")] + data[:4]  # cut after 4 of 10 cameras
    path.write_text("\n".join(kept) + "\n")
    with pytest.raises(DataError, match=r"images\.txt: line \d+: image '0004\.png' uses camera 5, which is not "
                                        r"defined \(cameras\.txt defines 4 camera\(s\); is it truncated\?\)"):
        read_colmap(scene_copy, ParseOptions())


def _edit_first_data_line(path: Path, column: int, value: str) -> int:
    """Set field ``column`` of the first data line of a COLMAP text file; returns its line number."""
    lines = path.read_text().splitlines()
    index = next(i for i, ln in enumerate(lines) if ln and not ln.startswith("#"))
    fields = lines[index].split()
    fields[column] = value
    lines[index] = " ".join(fields)
    path.write_text("\n".join(lines) + "\n")
    return index + 1


@pytest.mark.parametrize("value, problem", [("nan", "is not a finite number"), ("inf", "is not a finite number"),
                                            ("1.0x", "is not a number")])
def test_bad_number_in_points3d_txt_names_the_file_and_line(scene_copy: Path, value: str, problem: str) -> None:
    path = scene_copy / "sparse" / "0" / "points3D.txt"
    line = _edit_first_data_line(path, 2, value)
    with pytest.raises(DataError) as info:
        read_colmap(scene_copy, ParseOptions())
    message = str(info.value)
    assert message.startswith(f"{path}: line {line} (point ") and f"{value!r} {problem}" in message
    assert "\n" not in message and "Check failed" not in message  # not pycolmap's internal check


def test_nan_point_in_points3d_bin_is_left_out_with_the_file_named(scene_copy: Path) -> None:
    def nan_point(rec: pycolmap.Reconstruction) -> None:
        rec.points3D[min(rec.point3D_ids())].xyz = np.array([np.nan, 0.0, 0.0])

    _rewrite_model(scene_copy, nan_point, binary=True)
    path = scene_copy / "sparse" / "0" / "points3D.bin"
    with pytest.warns(UserWarning, match=rf"{path}: left out 1 of 400 points with non-finite coordinates"):
        scene = read_colmap(scene_copy, ParseOptions())
    assert scene.points.shape == (399, 3) and np.isfinite(scene.points).all()


@pytest.mark.parametrize("name", ["cameras", "images", "points3D"])
def test_truncated_bin_file_names_the_file_and_the_record(scene_copy: Path, name: str) -> None:
    _rewrite_model(scene_copy, lambda rec: None, binary=True)
    path = scene_copy / "sparse" / "0" / f"{name}.bin"
    data = path.read_bytes()
    what = {"cameras": "camera", "images": "image", "points3D": "point"}[name]
    for cut in (len(data) // 2, len(data) - 1):
        path.write_bytes(data[:cut])
        with pytest.raises(DataError, match=rf"^{path}: truncated: the file \({cut} bytes\) ends inside {what} "
                                            rf"\d+ of the \d+ its header announces$"):
            read_colmap(scene_copy, ParseOptions())
    path.write_bytes(data[:3])
    with pytest.raises(DataError, match=rf"^{path}: truncated: 3 bytes, too short for the record count$"):
        read_colmap(scene_copy, ParseOptions())
    path.write_bytes(data + b"junk")
    with pytest.raises(DataError, match=rf"^{path}: 4 bytes follow the last of its \d+ {what}s"):
        read_colmap(scene_copy, ParseOptions())


def test_images_on_disk_missing_from_the_model_are_counted(scene_copy: Path) -> None:
    path = scene_copy / "sparse" / "0" / "images.txt"
    lines = path.read_text().splitlines()
    header = [ln for ln in lines if ln.startswith("#")]
    body = [ln for ln in lines if not ln.startswith("#")]
    path.write_text("\n".join(header + body[:6]) + "\n")  # 3 images: pose line + points line each
    frames = scene_copy / "sparse" / "0" / "frames.txt"
    frame_lines = frames.read_text().splitlines()
    frames.write_text("\n".join([ln for ln in frame_lines if ln.startswith("#")]
                                + [ln for ln in frame_lines if not ln.startswith("#")][:3]) + "\n")
    (scene_copy / "split.json").unlink()  # the built-in split names all ten
    with pytest.warns(UserWarning, match=r"images: 7 of 10 images are not in the COLMAP model and are not used "
                                         r"\(e\.g\. 0003\.png, 0004\.png, 0005\.png\)"):
        scene = read_colmap(scene_copy, ParseOptions())
    assert [im.name for im in scene.images] == ["0000.png", "0001.png", "0002.png"]


def _tree(root: Path) -> dict[str, tuple[int, int, bytes]]:
    """Every file and folder under ``root``: (size, mtime_ns, content) by relative path."""
    out = {}
    for path in sorted(root.rglob("*")):
        info = path.lstat()
        content = path.read_bytes() if path.is_file() else b""
        out[path.relative_to(root).as_posix()] = (info.st_size, info.st_mtime_ns, content)
    return out


def test_a_training_run_leaves_the_dataset_folder_unchanged(scene_copy: Path, tmp_path: Path) -> None:
    """Undistortion and resizing caches go to the cache root, never into the user's dataset."""
    from exploregs_plugin.engine.trainer import TrainerConfig

    _rewrite_model(scene_copy, _simple_radial(0.05))
    before, folder_stamp = _tree(scene_copy), scene_copy.stat().st_mtime_ns
    config = TrainerConfig(data=str(scene_copy), data_factor=2, max_steps=2, run_dir=tmp_path / "run", quiet=True,
                           tensorboard=False, eval_count=1, save_eval_images=False)
    config.setup().train()
    assert _tree(scene_copy) == before and scene_copy.stat().st_mtime_ns == folder_stamp
    assert list((tmp_path / "run").iterdir())  # the run did write, elsewhere


def test_grayscale_16bit_and_rgba_images_are_converted_and_said_once(scene_copy: Path, tmp_path: Path, capsys) -> None:
    import torch

    from exploregs_plugin.data import DataManagerConfig

    images = scene_copy / "images"
    rgb = {name: np.asarray(Image.open(images / name).convert("RGB")) for name in ("0001.png", "0002.png", "0003.png")}
    gray = rgb["0001.png"][..., 1]
    Image.fromarray(gray, mode="L").save(images / "0001.png")
    gray16 = (np.arange(64 * 48, dtype=np.uint16).reshape(48, 64) * 21)
    Image.fromarray(gray16).save(images / "0002.png")  # opens as I;16
    alpha = np.full((48, 64, 1), 128, np.uint8)
    Image.fromarray(np.concatenate([rgb["0003.png"], alpha], axis=2), mode="RGBA").save(images / "0003.png")
    capsys.readouterr()
    dm = DataManagerConfig(data=str(scene_copy), test_every=0, use_dataset_split=False, background="white",
                           cache_dir=str(tmp_path / "cache")).setup()
    err = capsys.readouterr().err
    notes = [line for line in err.splitlines() if line.startswith("note:")]
    assert notes == [f"note: {scene_copy}: 1 of 10 images are grayscale (e.g. 0001.png): the gray value is used for "
                     f"R, G and B; 1 of 10 images are 16-bit grayscale (e.g. 0002.png): scaled to 8 bits (value / 257) "
                     f"and used for R, G and B; 1 of 10 images have an alpha channel (e.g. 0003.png): composited on the "
                     f"background colour (--datamanager.background)"]
    names = [c.name for c in dm.train_cameras]
    image = {name: (dm.train_item(names.index(name))[1] * 255).round().to(torch.uint8).numpy()
             for name in ("0001.png", "0002.png", "0003.png")}
    assert (image["0001.png"] == gray[..., None]).all()
    assert (image["0002.png"] == np.round(gray16 / 257).astype(np.uint8)[..., None]).all()
    expected = np.round(rgb["0003.png"] * (128 / 255) + 255 * (1 - 128 / 255)).astype(np.uint8)
    assert np.abs(image["0003.png"].astype(int) - expected).max() <= 1
    # a plain RGB dataset says nothing
    from exploregs_plugin.data import parse_dataset

    capsys.readouterr()
    parse_dataset("builtin:tiny", ParseOptions())
    assert "note:" not in capsys.readouterr().err


def test_float_image_is_refused_clearly(scene_copy: Path) -> None:
    Image.fromarray(np.zeros((48, 64), np.float32), mode="F").save(scene_copy / "images" / "0004.tiff")
    (scene_copy / "images" / "0004.tiff").rename(scene_copy / "images" / "0004.png")
    with pytest.raises(DataError, match=r"0004\.png: image has 32-bit float pixels"):
        read_colmap(scene_copy, ParseOptions())
