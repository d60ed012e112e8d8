"""transforms.json: export/import equals COLMAP, Blender and instant-ngp variants, bad input."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from exploregs_plugin.data import DataError, ParseOptions, parse_dataset, read_transforms, write_transforms
from exploregs_plugin.data.transforms_json import write_ply_points


@pytest.fixture()
def exported(tiny_scene_dir: Path, tmp_path: Path) -> Path:
    """The tiny scene exported as transforms.json (images referenced in place)."""
    scene = parse_dataset(str(tiny_scene_dir), ParseOptions())
    return write_transforms(scene, tmp_path / "export" / "transforms.json")


def _edit(path: Path, change) -> None:
    meta = json.loads(path.read_text())
    change(meta)
    path.write_text(json.dumps(meta))


def test_transforms_export_equals_colmap_after_conversion(tiny_scene_dir: Path, exported: Path) -> None:
    colmap = parse_dataset(str(tiny_scene_dir), ParseOptions())
    back = parse_dataset(str(exported), ParseOptions())
    assert len(back.images) == len(colmap.images)
    for a, b in zip(colmap.images, back.images):
        assert Path(b.name).name == a.name and b.path.resolve() == a.path.resolve()
        np.testing.assert_allclose(b.K, a.K, atol=1e-12)
        np.testing.assert_allclose(b.viewmat, a.viewmat, atol=1e-10)
    np.testing.assert_allclose(back.points, colmap.points, atol=1e-10)
    np.testing.assert_allclose(back.points_rgb, colmap.points_rgb, atol=1e-12)
    np.testing.assert_allclose(back.normalization.translation, colmap.normalization.translation, atol=1e-10)
    assert back.normalization.scale == pytest.approx(colmap.normalization.scale, rel=1e-12)
    assert back.scene_extent == pytest.approx(colmap.scene_extent, rel=1e-12)
    assert [Path(n).name for n in back.split["test"]] == colmap.split["test"]


def _blender_folder(root: Path) -> Path:
    """A 2-train/1-test Blender-style dataset with RGBA images and extension-less paths."""
    root.mkdir()
    angle = 2 * np.arctan(0.5)  # fx = w / 2 / tan(angle / 2) = w
    for split, count in (("train", 2), ("test", 1)):
        (root / split).mkdir()
        frames = []
        for i in range(count):
            rgba = np.zeros((8, 10, 4), dtype=np.uint8)
            rgba[..., 0] = 200
            rgba[:, :5, 3] = 255  # left half opaque red, right half transparent
            Image.fromarray(rgba, "RGBA").save(root / split / f"r_{i}.png")
            c2w = np.eye(4)
            c2w[:3, 3] = [0.5 * i, 0.0, 4.0]  # OpenGL camera looking down -z at the origin
            frames.append({"file_path": f"./{split}/r_{i}", "transform_matrix": c2w.tolist()})
        (root / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": angle, "frames": frames}))
    return root


def test_blender_variant_opengl_rgba_and_split(tmp_path: Path) -> None:
    root = _blender_folder(tmp_path / "blender")
    bg = np.array([0.0, 1.0, 0.0])
    scene = read_transforms(root, ParseOptions(background=bg))
    assert [im.name for im in scene.images] == ["test/r_0.png", "train/r_0.png", "train/r_1.png"]
    assert scene.split == {"train": ["train/r_0.png", "train/r_1.png"], "test": ["test/r_0.png"]}
    im = scene.images[1]
    np.testing.assert_allclose(im.K, [[10, 0, 5], [0, 10, 4], [0, 0, 1]], atol=1e-12)
    # OpenGL camera at z=4 looking down -z: in OpenCV the origin is 4 units ahead, at the centre.
    cam = im.viewmat[:3, :3] @ np.zeros(3) + im.viewmat[:3, 3]
    np.testing.assert_allclose(cam, [0, 0, 4], atol=1e-12)
    up_world = im.viewmat[:3, :3] @ np.array([0.0, 1.0, 0.0])
    assert up_world[1] < 0  # world up (OpenGL y) is image up = -y in OpenCV
    assert scene.points is None  # no point cloud: the datamanager initialises randomly
    from exploregs_plugin.data.images import read_image

    pixels = read_image(im.path, bg)
    np.testing.assert_array_equal(pixels[0, 0], [200, 0, 0])
    np.testing.assert_array_equal(pixels[0, 9], [0, 255, 0])


def test_intrinsics_for_another_resolution_are_scaled(exported: Path) -> None:
    before = read_transforms(exported, ParseOptions())

    def double(meta):
        for f in meta["frames"]:
            for k in ("fl_x", "fl_y", "cx", "cy", "w", "h"):
                f[k] = f[k] * 2

    _edit(exported, double)
    after = read_transforms(exported, ParseOptions())
    np.testing.assert_allclose(after.images[0].K, before.images[0].K, atol=1e-12)
    assert (after.images[0].width, after.images[0].height) == (64, 48)


def test_top_level_intrinsics_with_frame_overrides(exported: Path) -> None:
    def hoist(meta):
        first = dict(meta["frames"][0])
        for k in ("fl_x", "fl_y", "cx", "cy", "w", "h"):
            meta[k] = first[k]
            for f in meta["frames"]:
                del f[k]
        meta["frames"][1]["fl_x"] = 40.0  # per-frame override

    _edit(exported, hoist)
    scene = read_transforms(exported, ParseOptions())
    assert scene.images[1].K[0, 0] == 40.0 and scene.images[0].K[0, 0] != 40.0


def test_distortion_is_undistorted_or_refused(exported: Path) -> None:
    _edit(exported, lambda m: [f.update(k1=0.05, k2=-0.01, p1=0.001, p2=0.0) for f in m["frames"]])
    with pytest.raises(DataError, match="OPENCV has lens distortion"):
        read_transforms(exported, ParseOptions(undistort=False))
    scene = read_transforms(exported, ParseOptions())
    im = scene.images[0]
    assert im.path.parent.name == "undistorted_f1" and not (exported.parent / ".exploregs").exists()
    assert ".." not in im.path.parts  # images outside the dataset folder get flat cache names
    assert im.path.name.endswith(".png") and "0000" in im.path.name
    with Image.open(im.path) as pic:
        assert pic.size == (im.width, im.height)


def test_ply_points_and_empty_ply(exported: Path) -> None:
    write_ply_points(exported.parent / "points3D.ply", np.array([[1.0, 2.0, 3.0]]), np.array([[1.0, 0.5, 0.0]]))
    scene = read_transforms(exported, ParseOptions())
    np.testing.assert_allclose(scene.points, [[1, 2, 3]])
    np.testing.assert_allclose(scene.points_rgb, [[1.0, 128 / 255, 0.0]])
    write_ply_points(exported.parent / "points3D.ply", np.zeros((0, 3)), np.zeros((0, 3)))
    with pytest.warns(UserWarning, match="empty point cloud; using random initialisation"):
        scene = read_transforms(exported, ParseOptions())
    assert scene.points is None  # the datamanager initialises randomly (tests/test_data_datamanager.py)


# ---- bad input ----

def test_missing_frames_key(tmp_path: Path) -> None:
    path = tmp_path / "transforms.json"
    path.write_text(json.dumps({"camera_angle_x": 0.7}))
    with pytest.raises(DataError, match=r"transforms\.json: missing required key 'frames'"):
        read_transforms(path, ParseOptions())


def test_invalid_json(tmp_path: Path) -> None:
    path = tmp_path / "transforms.json"
    path.write_text("{not json")
    with pytest.raises(DataError, match="not valid JSON"):
        read_transforms(path, ParseOptions())


def test_zero_frames(tmp_path: Path) -> None:
    path = tmp_path / "transforms.json"
    path.write_text(json.dumps({"camera_angle_x": 0.7, "frames": []}))
    with pytest.raises(DataError, match="zero images"):
        read_transforms(path, ParseOptions())


def test_frame_missing_keys(exported: Path) -> None:
    _edit(exported, lambda m: m["frames"][2].pop("transform_matrix"))
    with pytest.raises(DataError, match=r"frame 2\): missing required key 'transform_matrix'"):
        read_transforms(exported, ParseOptions())


def test_missing_intrinsics(exported: Path) -> None:
    _edit(exported, lambda m: [f.pop("fl_x") and f.pop("fl_y") for f in m["frames"]])
    with pytest.raises(DataError, match="missing intrinsics: need 'fl_x'"):
        read_transforms(exported, ParseOptions())


def test_non_finite_transform(exported: Path) -> None:
    _edit(exported, lambda m: m["frames"][1]["transform_matrix"][0].__setitem__(3, float("nan")))
    with pytest.raises(DataError, match=r"frame 1\): camera pose is not finite"):
        read_transforms(exported, ParseOptions())


def test_missing_image_file(exported: Path) -> None:
    _edit(exported, lambda m: m["frames"][0].__setitem__("file_path", "nowhere/x.png"))
    with pytest.raises(DataError, match=r"frame 0\): file_path 'nowhere/x\.png' names no image: .*x\.png does not exist$"):
        read_transforms(exported, ParseOptions())


def test_wrong_aspect_ratio(exported: Path) -> None:
    _edit(exported, lambda m: m["frames"][0].__setitem__("w", 100))
    with pytest.raises(DataError, match="does not match the camera's aspect ratio"):
        read_transforms(exported, ParseOptions())


def test_rgba_alpha_reaches_training_and_random_background(tmp_path: Path) -> None:
    """The DataManager keeps the alpha channel, so a random background re-composites exactly:
    target on background b = c a + b (1 - a)."""
    import torch

    from exploregs_plugin.data import DataManagerConfig
    from exploregs_plugin.engine.pipeline import Pipeline, PipelineConfig
    from exploregs_plugin.schedule import ScheduleConfig

    root = _blender_folder(tmp_path / "blender")
    dm = DataManagerConfig(data=str(root), background=(0.0, 0.0, 1.0), n_random_points=50,
                           cache_dir=str(tmp_path / "cache")).setup()
    assert dm.has_alpha
    _, image, extras = dm.train_item(0)
    alpha = extras["alpha"]
    assert alpha.shape == (8, 10, 1)
    assert torch.equal(alpha[:, :5], torch.ones(8, 5, 1)) and torch.equal(alpha[:, 5:], torch.zeros(8, 5, 1))
    assert torch.allclose(image[0, 9], torch.tensor([0.0, 0.0, 1.0]))  # transparent -> dataset background

    pipeline = Pipeline(PipelineConfig(datamanager=DataManagerConfig(
        data=str(root), background=(0.0, 0.0, 1.0), n_random_points=50, cache_dir=str(tmp_path / "cache")),
        random_background=True), ScheduleConfig().resolve(10), seed=0)
    seen = {}
    real_render = pipeline.model.render

    def spy(camera, sh_degree, background):
        seen["background"] = background
        return real_render(camera, sh_degree, background)

    pipeline.model.render = spy

    def capture(view):  # a loss term that sees what every term sees, and adds nothing
        seen["target"] = view.target
        return view.image.sum() * 0.0, {}

    pipeline.loss_terms = [*pipeline.loss_terms, capture]
    pipeline.train_step(0)
    b = seen["background"]
    assert not torch.allclose(b, torch.tensor([0.0, 0.0, 1.0]))
    expected_right = b.expand(8, 5, 3)  # fully transparent half shows the random background
    assert torch.allclose(seen["target"][:, 5:], expected_right, atol=1e-6)
    assert torch.allclose(seen["target"][:, :5], torch.tensor([200 / 255, 0.0, 0.0]).expand(8, 5, 3), atol=1e-6)


def test_random_background_refused_without_alpha(tiny_scene_dir: Path) -> None:
    from exploregs_plugin.data import DataManagerConfig
    from exploregs_plugin.engine.pipeline import PipelineConfig
    from exploregs_plugin.schedule import ScheduleConfig

    config = PipelineConfig(datamanager=DataManagerConfig(data="builtin:tiny"), random_background=True)
    with pytest.raises(ValueError, match="random_background needs .* alpha"):
        config.setup(ScheduleConfig().resolve(10), seed=0)
