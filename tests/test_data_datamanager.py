"""DataManager: the brief's interface, splits, seeded order, resume, normalisation, bad config."""

from __future__ import annotations

import io
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from exploregs_plugin.cameras import Camera
from exploregs_plugin.data import DataError, DataManagerConfig


def test_interface_types_and_shapes(tiny_dm) -> None:
    dm = tiny_dm
    assert dm.scene_name == "tiny"
    assert len(dm.train_cameras) == 8 and len(dm.test_cameras) == 2  # the scene's split.json
    assert [c.name for c in dm.test_cameras] == ["0000.png", "0008.png"]
    for cam in dm.train_cameras + dm.test_cameras:
        assert isinstance(cam, Camera) and cam.viewmat.dtype == torch.float32 and cam.K.dtype == torch.float32
        assert cam.viewmat.shape == (4, 4) and cam.K.shape == (3, 3) and (cam.width, cam.height) == (64, 48)
    cam, image, extras = dm.train_item(2)
    assert cam is dm.train_cameras[2]
    assert image.shape == (48, 64, 3) and image.dtype == torch.float32
    assert 0.0 <= float(image.min()) and float(image.max()) <= 1.0 and float(image.std()) > 0.05
    assert extras["depth"].shape == (48, 64, 1) and extras["depth"].dtype == torch.float32
    assert float(extras["depth"].min()) > 0
    assert {k: v.dtype for k, v in extras["masks"].items()} == {k: torch.bool for k in ("other", "far", "occluded")}
    assert dm.points.dtype == torch.float32 and dm.points.shape == (400, 3)
    assert dm.points_rgb.shape == (400, 3) and 0 <= float(dm.points_rgb.min()) <= float(dm.points_rgb.max()) <= 1
    translation, scale = dm.normalization
    assert translation.shape == (3,) and isinstance(scale, float) and scale > 0
    assert dm.background.dtype == torch.float32 and dm.background.tolist() == [0.0, 0.0, 0.0]


def test_normalised_cameras_and_extent(tiny_dm) -> None:
    centers = torch.stack([c.camera_center for c in tiny_dm.train_cameras + tiny_dm.test_cameras])
    assert torch.allclose(centers.mean(0), torch.zeros(3), atol=1e-5)
    radius = float((centers - centers.mean(0)).norm(dim=1).max())
    assert radius == pytest.approx(1.0, abs=1e-5)
    assert tiny_dm.scene_extent == pytest.approx(1.1 * radius, abs=1e-5)


def test_unnormalised_keeps_file_units(tiny_scene_dir: Path) -> None:
    dm = DataManagerConfig(data="builtin:tiny", normalize=False).setup()
    translation, scale = dm.normalization
    assert scale == 1.0 and translation.abs().max() == 0
    centers = torch.stack([c.camera_center for c in dm.train_cameras + dm.test_cameras]).double()
    radius = float((centers - centers.mean(0)).norm(dim=1).max())
    assert dm.scene_extent == pytest.approx(1.1 * radius, rel=1e-5) and radius > 2.0


def test_test_every_split(tiny_scene_dir: Path) -> None:
    dm = DataManagerConfig(data=str(tiny_scene_dir), use_dataset_split=False, test_every=3).setup()
    assert [c.name for c in dm.test_cameras] == ["0000.png", "0003.png", "0006.png", "0009.png"]
    assert len(dm.train_cameras) == 6
    dm = DataManagerConfig(data=str(tiny_scene_dir), use_dataset_split=False, test_every=0).setup()
    assert len(dm.train_cameras) == 10 and dm.test_cameras == []


def test_next_train_is_a_seeded_permutation_per_epoch(tiny_scene_dir: Path) -> None:
    dm = DataManagerConfig(data="builtin:tiny", seed=4).setup()
    n = len(dm.train_cameras)
    first = [dm.next_train()[0] for _ in range(n)]
    second = [dm.next_train()[0] for _ in range(n)]
    assert sorted(first) == list(range(n)) and sorted(second) == list(range(n))
    assert first != second and dm.epoch == 1
    index, cam, image, extras = DataManagerConfig(data="builtin:tiny", seed=4).setup().next_train()
    assert index == first[0] and cam is not None and image.shape == (48, 64, 3) and "depth" in extras
    other = DataManagerConfig(data="builtin:tiny", seed=5).setup()
    assert [other.next_train()[0] for _ in range(2 * n)] != first + second


def test_state_dict_resumes_the_same_order(tiny_scene_dir: Path) -> None:
    dm = DataManagerConfig(data="builtin:tiny", seed=1).setup()
    for _ in range(10):
        dm.next_train()
    buffer = io.BytesIO()
    torch.save(dm.state_dict(), buffer)
    expected = [dm.next_train()[0] for _ in range(20)]
    resumed = DataManagerConfig(data="builtin:tiny", seed=1).setup()
    buffer.seek(0)
    resumed.load_state_dict(torch.load(buffer, weights_only=True))
    assert [resumed.next_train()[0] for _ in range(20)] == expected


def test_state_dict_from_other_images_is_refused(tiny_scene_dir: Path) -> None:
    dm = DataManagerConfig(data="builtin:tiny").setup()
    state = dm.state_dict()
    state["train_names"] = state["train_names"][:-1]
    with pytest.raises(DataError, match="different training images"):
        dm.load_state_dict(state)


def test_data_factor_resizes_images_depths_and_masks(tiny_scene_dir: Path) -> None:
    full = DataManagerConfig(data="builtin:tiny").setup()
    half = DataManagerConfig(data="builtin:tiny", data_factor=2).setup()
    cam, image, extras = half.test_item(0)
    assert (cam.width, cam.height) == (32, 24) and image.shape == (24, 32, 3)
    assert extras["depth"].shape == (24, 32, 1) and extras["masks"]["far"].shape == (24, 32)
    assert torch.allclose(cam.K[:2], full.test_cameras[0].K[:2] * 0.5)
    # nearest-neighbour downsampling keeps depth values that exist at full resolution
    full_depth = full.test_item(0)[2]["depth"]
    assert bool(torch.isin(extras["depth"].flatten(), full_depth.flatten()).all())


def test_background_is_reported(tiny_scene_dir: Path) -> None:
    dm = DataManagerConfig(data="builtin:tiny", background=(1.0, 1.0, 1.0)).setup()
    assert dm.background.tolist() == [1.0, 1.0, 1.0]


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"data_factor": 0}, "--data-factor: must be an integer >= 1"),
        ({"test_every": -1}, "--test-every: must be >= 0"),
        ({"background": (0.0, 2.0, 0.0)}, "--background: must be three values in"),
        ({"data": "/definitely/not/here"}, "path does not exist"),
        ({"data": "builtin:unknown"}, "unknown built-in scene"),
        ({"use_dataset_split": False, "test_every": 1}, "no training images"),
    ],
)
def test_bad_config_values(tiny_scene_dir: Path, kwargs: dict, message: str) -> None:
    config = DataManagerConfig(data="builtin:tiny")
    for key, value in kwargs.items():
        setattr(config, key, value)
    with pytest.raises(DataError, match=message):
        config.setup()


def test_folder_that_is_not_a_dataset(tmp_path: Path) -> None:
    with pytest.raises(DataError, match="not a dataset"):
        DataManagerConfig(data=str(tmp_path)).setup()
    (tmp_path / "notes.txt").write_text("x")
    with pytest.raises(DataError, match="must be a transforms.json"):
        DataManagerConfig(data=str(tmp_path / "notes.txt")).setup()


def test_depth_scaled_into_normalised_units(tiny_scene_dir: Path) -> None:
    dm = DataManagerConfig(data="builtin:tiny").setup()
    raw = np.load(tiny_scene_dir / "depths" / "0000.npy")
    depth = dm.test_item(0)[2]["depth"][..., 0].numpy()
    np.testing.assert_allclose(depth, raw * dm.normalization[1], rtol=1e-6)


def test_random_init_replaces_the_points_inside_the_camera_bounds(tiny_scene_dir: Path) -> None:
    base = DataManagerConfig(data="builtin:tiny")
    with_points = base.setup()
    forced = replace(base, random_init=True, random_init_mode="box", n_random_points=300, seed=4).setup()
    assert forced.points.shape == (300, 3) and forced.points_rgb.shape == (300, 3)
    assert not torch.equal(forced.points[:1], with_points.points[:1])
    from exploregs_plugin.data.random_init import focus_point

    images = forced.parsed.images
    centers = np.stack([im.camera_center for im in images])
    focus = focus_point(centers, np.stack([im.viewmat[2, :3] for im in images]))
    corners = np.concatenate([centers, focus[None]])
    pad = 0.1 * (corners.max(0) - corners.min(0)).max()
    pts = forced.points.numpy()
    assert (pts >= corners.min(0) - pad - 1e-5).all() and (pts <= corners.max(0) + pad + 1e-5).all()
    assert (pts.max(0) - pts.min(0) > 0.5 * (corners.max(0) - corners.min(0))).all()  # fills the box
    again = replace(base, random_init=True, random_init_mode="box", n_random_points=300, seed=4).setup()
    assert torch.equal(again.points, forced.points)  # seeded


def test_frustum_init_puts_points_on_training_pixels_with_their_colours(tiny_scene_dir: Path) -> None:
    config = DataManagerConfig(data="builtin:tiny", random_init=True, n_random_points=200, seed=2,
                               random_init_depth=(0.5, 4.0))
    dm = config.setup()
    near, far = 0.5 * dm.scene_extent, 4.0 * dm.scene_extent
    pts, rgb = dm.points.double(), dm.points_rgb.double()
    assert pts.shape == (200, 3) and bool(((rgb >= 0) & (rgb <= 1)).all())
    explained = torch.zeros(200, dtype=torch.bool)
    depths = []
    for i, camera in enumerate(dm.train_cameras):
        image = dm.train_item(i)[1].double()
        cam = pts @ camera.viewmat[:3, :3].double().T + camera.viewmat[:3, 3].double()
        z = cam[:, 2]
        uv = (cam @ camera.K.double().T)[:, :2] / z.clamp_min(1e-9)[:, None]
        px, py = torch.floor(uv[:, 0]).long(), torch.floor(uv[:, 1]).long()
        inside = (z > 0) & (px >= 0) & (px < camera.width) & (py >= 0) & (py < camera.height)
        centred = ((uv - torch.floor(uv) - 0.5).abs() < 1e-4).all(dim=1)  # on a pixel centre
        hit = inside & centred & (z >= near * (1 - 1e-5)) & (z <= far * (1 + 1e-5))
        same = torch.zeros(200, dtype=torch.bool)
        same[hit] = (image[py[hit], px[hit]] - rgb[hit]).abs().max(dim=1).values < 1e-6
        depths.append(z[same & ~explained])
        explained |= same
    assert bool(explained.all())  # every point sits on a training pixel's ray and has its colour
    z = torch.cat(depths).log()
    # log-uniform depths: mean log depth near the middle of [log near, log far]
    assert abs(float(z.mean()) - 0.5 * (math.log(near) + math.log(far))) < 0.2 * math.log(far / near)
    again = config.setup()
    assert torch.equal(again.points, dm.points)
    with pytest.raises(DataError, match="random-init-depth"):
        replace(config, random_init_depth=(2.0, 1.0)).setup()


@pytest.mark.parametrize("split", ["train", "test"])
def test_an_item_on_a_device_is_the_host_item_moved(tiny_dm, split):
    # the pipeline and evaluation ask for their device's copy (converted from uint8 there): the same values
    item = getattr(tiny_dm, f"{split}_item")
    for index in (0, len(getattr(tiny_dm, f"{split}_cameras")) - 1):
        camera, host, _ = item(index)
        camera_d, on_device, _ = item(index, torch.device("cpu"))
        assert camera_d is camera and on_device.dtype == torch.float32 and torch.equal(on_device, host)
        assert float(host.min()) >= 0.0 and float(host.max()) <= 1.0 and float(host.max()) > 0.0
