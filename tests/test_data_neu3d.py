"""Neu3D / DyNeRF multi-view video datasets and the built-in dynamic scene."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from exploregs_plugin.data import DataError, DataManagerConfig, ParseOptions
from exploregs_plugin.data.builtin.presets import ensure_builtin, preset_by_name
from exploregs_plugin.data.builtin.dynamic import generate_dynamic, region_labels
from exploregs_plugin.data.dataparser import resolve_data
from exploregs_plugin.data.neu3d import llff_to_viewmat, read_neu3d, viewmat_to_llff
from exploregs_plugin.data.parsed import REGION_LABELS
from exploregs_plugin.data.builtin.layouts import look_at

WIDTH, HEIGHT, FOCAL = 32, 24, 30.0


def _c2ws(n: int) -> list[np.ndarray]:
    return [look_at(np.array([3.0 * np.cos(a), 3.0 * np.sin(a), 1.0]), np.zeros(3))
            for a in np.pi + np.linspace(-0.4, 0.4, n)]


def _poses(c2ws: list[np.ndarray], width: int = WIDTH, height: int = HEIGHT) -> np.ndarray:
    rows = []
    for c2w in c2ws:
        llff = np.concatenate([viewmat_to_llff(np.linalg.inv(c2w)), [[height], [width], [FOCAL]]], axis=1)
        rows.append(np.concatenate([llff.reshape(-1), [0.5, 20.0]]))
    return np.stack(rows)


def _frame(cam: int, frame: int) -> np.ndarray:
    """A frame whose pixels encode (camera, frame): cheap to check after decoding."""
    image = np.zeros((HEIGHT, WIDTH, 3), np.uint8)
    image[..., 0] = 40 * cam + 10
    image[..., 1] = 20 * frame + 5
    image[:, : WIDTH // 2, 2] = 200
    return image


def make_frames_layout(root: Path, n_cams: int = 3, n_frames: int = 4, frames: dict[int, int] | None = None) -> Path:
    root.mkdir(parents=True, exist_ok=True)
    np.save(root / "poses_bounds.npy", _poses(_c2ws(n_cams)))
    for c in range(n_cams):
        folder = root / f"cam{c:02d}" / "images"
        folder.mkdir(parents=True)
        for f in range((frames or {}).get(c, n_frames)):
            Image.fromarray(_frame(c, f)).save(folder / f"{f:04d}.png")
    return root


def make_video_layout(root: Path, n_cams: int = 2, n_frames: int = 5) -> Path:
    import av

    root.mkdir(parents=True, exist_ok=True)
    np.save(root / "poses_bounds.npy", _poses(_c2ws(n_cams)))
    for c in range(n_cams):
        with av.open(str(root / f"cam{c:02d}.mp4"), mode="w") as container:
            stream = container.add_stream("libx264", rate=30)
            stream.width, stream.height, stream.pix_fmt = WIDTH, HEIGHT, "yuv444p"
            stream.options = {"crf": "0"}  # lossless, so the decoded pixels can be checked
            for f in range(n_frames):
                for packet in stream.encode(av.VideoFrame.from_ndarray(_frame(c, f), format="rgb24")):
                    container.mux(packet)
            for packet in stream.encode():
                container.mux(packet)
    return root


def test_llff_round_trip_and_axes():
    c2w = _c2ws(1)[0]
    viewmat = np.linalg.inv(c2w)
    llff = viewmat_to_llff(viewmat)
    assert np.allclose(llff_to_viewmat(llff), viewmat)
    # LLFF columns: down (= OpenCV y), right (= x), back (= -z), then the centre
    assert np.allclose(llff[:, 0], c2w[:3, 1]) and np.allclose(llff[:, 1], c2w[:3, 0])
    assert np.allclose(llff[:, 2], -c2w[:3, 2]) and np.allclose(llff[:, 3], c2w[:3, 3])


def test_frames_layout(tmp_path):
    root = make_frames_layout(tmp_path / "scene")
    assert resolve_data(str(root), tmp_path / "cache") == ("neu3d", root)
    scene = read_neu3d(root, ParseOptions(cache_root=tmp_path / "cache"))
    assert len(scene.images) == 12
    by_name = {im.name: im for im in scene.images}
    im = by_name["cam01/0002.png"]
    assert im.time == pytest.approx(2 / 3)
    assert (im.width, im.height) == (WIDTH, HEIGHT)
    assert np.allclose(im.K, [[FOCAL, 0, WIDTH / 2], [0, FOCAL, HEIGHT / 2], [0, 0, 1]])
    assert np.allclose(im.viewmat, np.linalg.inv(_c2ws(3)[1]))
    assert scene.split["test"] == [f"cam00/{f:04d}.png" for f in range(4)]
    assert len(scene.split["train"]) == 8 and not any(n.startswith("cam00/") for n in scene.split["train"])
    assert scene.points is None  # no points3D.ply: the datamanager draws random points


def test_datamanager_on_frames_with_stride_and_factor(tmp_path):
    root = make_frames_layout(tmp_path / "scene", n_frames=5)
    dm = DataManagerConfig(data=str(root), frame_stride=2, data_factor=2, n_random_points=50,
                           cache_dir=str(tmp_path / "cache")).setup()
    assert dm.is_dynamic
    assert [c.name for c in dm.test_cameras] == ["cam00/0000.png", "cam00/0002.png", "cam00/0004.png"]
    assert [c.time for c in dm.test_cameras] == pytest.approx([0.0, 0.5, 1.0])
    camera, image, _ = dm.test_item(1)
    assert image.shape == (HEIGHT // 2, WIDTH // 2, 3)
    assert float(camera.K[0, 0]) == pytest.approx(FOCAL / 2)
    # the pixels are the frame's: green channel 20 * frame + 5
    assert float(image[..., 1].mean()) * 255 == pytest.approx(45, abs=1)
    assert dm.points.shape == (50, 3)


def test_video_layout_is_decoded_once(tmp_path):
    root = make_video_layout(tmp_path / "scene")
    cache = tmp_path / "cache"
    scene = read_neu3d(root, ParseOptions(cache_root=cache))
    assert len(scene.images) == 10
    frame = next(im for im in scene.images if im.name == "cam01/0003.png")
    assert frame.time == pytest.approx(0.75)
    pixels = np.asarray(Image.open(frame.path).convert("RGB")).astype(int)
    assert np.abs(pixels - _frame(1, 3)).max() <= 3  # lossless up to the colour conversion
    marker = frame.path.parent / "frames.json"
    stamp = marker.stat().st_mtime_ns
    again = read_neu3d(root, ParseOptions(cache_root=cache))
    assert [im.path for im in again.images] == [im.path for im in scene.images]
    assert marker.stat().st_mtime_ns == stamp  # reused, not decoded again
    limited = read_neu3d(root, ParseOptions(cache_root=cache, max_frames=3))
    assert sorted({im.name.split("/")[1] for im in limited.images}) == ["0000.png", "0001.png", "0002.png"]
    assert max(im.time for im in limited.images) == pytest.approx(1.0)


def test_different_frame_counts_are_refused(tmp_path):
    root = make_frames_layout(tmp_path / "scene", frames={1: 3})
    with pytest.raises(DataError, match=r"different frame counts \(cam00: 4, cam01: 3, cam02: 4\)"):
        read_neu3d(root, ParseOptions(cache_root=tmp_path / "cache"))
    # the first frames of each camera are synchronised
    assert len(read_neu3d(root, ParseOptions(cache_root=tmp_path / "cache", max_frames=3)).images) == 9


def test_missing_or_bad_poses_are_refused(tmp_path):
    root = make_frames_layout(tmp_path / "scene")
    (root / "poses_bounds.npy").unlink()
    with pytest.raises(DataError, match="no poses_bounds.npy"):
        read_neu3d(root, ParseOptions(cache_root=tmp_path / "cache"))
    with pytest.raises(DataError, match="not a dataset"):
        resolve_data(str(root), tmp_path / "cache")
    np.save(root / "poses_bounds.npy", _poses(_c2ws(2)))
    with pytest.raises(DataError, match="has 2 poses but the folder has 3 cameras"):
        read_neu3d(root, ParseOptions(cache_root=tmp_path / "cache"))
    np.save(root / "poses_bounds.npy", np.zeros((3, 15)))
    with pytest.raises(DataError, match=r"expected an array \[cameras, 17\]"):
        read_neu3d(root, ParseOptions(cache_root=tmp_path / "cache"))
    bad = _poses(_c2ws(3))
    bad[1, 3] = np.nan
    np.save(root / "poses_bounds.npy", bad)
    with pytest.raises(DataError, match="NaN or infinite"):
        read_neu3d(root, ParseOptions(cache_root=tmp_path / "cache"))
    shutil.rmtree(root / "cam02")
    (root / "cam02").mkdir()
    np.save(root / "poses_bounds.npy", _poses(_c2ws(3)))
    with pytest.raises(DataError, match="holds no frames"):
        read_neu3d(root, ParseOptions(cache_root=tmp_path / "cache"))


def test_corrupt_video_is_named(tmp_path):
    root = make_frames_layout(tmp_path / "scene", n_cams=2)
    shutil.rmtree(root / "cam01")
    (root / "cam01.mp4").write_bytes(b"not a video at all")
    with pytest.raises(DataError, match=r"cam01\.mp4: video is unreadable"):
        read_neu3d(root, ParseOptions(cache_root=tmp_path / "cache"))


def test_builtin_dynamic_scene(exploregs_cache):
    path = ensure_builtin("dynamic-tiny", exploregs_cache / "scenes")
    meta = json.loads((path / "scene.json").read_text())
    assert meta["preset"]["n_cameras"] == 4 and meta["preset"]["n_frames"] == 6
    dm = DataManagerConfig(data="builtin:dynamic-tiny").setup()
    assert len(dm.test_cameras) == 6 and len(dm.train_cameras) == 18
    assert set(dm.regions) == {"other", "far", "occluded", "moving"}
    times = [c.time for c in dm.test_cameras]
    assert times == sorted(times) and times[0] == 0.0 and times[-1] == 1.0
    assert dm.points is not None and len(dm.points) > 100
    # the occluders move: frames of one camera differ where they are, not on the far skyline
    _, first, extras0 = dm.test_item(0)
    _, last, extras1 = dm.test_item(5)
    moving = extras0["masks"]["moving"] | extras1["masks"]["moving"]
    far = extras0["masks"]["far"] & extras1["masks"]["far"]
    assert bool(moving.any()) and bool(far.any())
    diff = (first - last).abs().mean(dim=-1)
    assert float(diff[moving].mean()) > 0.05
    # (a far pixel at an occluder's edge may see it in a sub-sample: the labels are the pixel centre's)
    assert float((diff[far] > 0).float().mean()) < 0.02


def test_dynamic_generation_is_deterministic_and_labels_follow_coverage():
    preset = preset_by_name("dynamic-tiny")
    a, b = generate_dynamic(preset), generate_dynamic(preset)
    assert np.array_equal(a.images, b.images) and np.array_equal(a.labels, b.labels)
    assert np.array_equal(a.points, b.points)
    # region_labels: moving wins; occluded = static content covered in >= the fraction of frames
    moving = np.zeros((1, 4, 1, 3), dtype=bool)
    moving[0, 0, 0, 0] = True  # pixel 0: covered in 1 of 4 frames
    moving[0, :, 0, 1] = [True, False, False, False]
    far = np.array([[[False, True, False]]])
    labels = region_labels(moving, far, occluded_fraction=0.25)
    assert labels[0, 0, 0, 0] == REGION_LABELS["moving"]
    assert labels[0, 1, 0, 0] == REGION_LABELS["occluded"]
    assert labels[0, 1, 0, 1] == REGION_LABELS["far"]  # far stays far
    assert labels[0, 1, 0, 2] == REGION_LABELS["other"]
