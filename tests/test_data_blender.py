"""Blender / NeRF-synthetic and D-NeRF folders (transforms_{train,val,test}.json): splits, alpha on
the chosen background, images without alpha, per-frame time for the dynamic methods, the cube
initialisation and one-line errors. Every dataset is a few tiny RGBA frames written here."""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
import tyro
from PIL import Image

from exploregs_plugin.data import DataError, DataManagerConfig, ParseOptions, read_transforms, write_transforms
from exploregs_plugin.data.backgrounds import border_shares, evident_background
from exploregs_plugin.data.random_init import cube_bounds, cube_points
from exploregs_plugin.engine.pipeline import PipelineConfig

W, H = 10, 8
ANGLE = 2 * math.atan(0.5)  # fx = (w / 2) / tan(angle / 2) = w
SPLITS = {"train": 4, "val": 2, "test": 3}
RADIUS = 4.0


def _c2w_gl(azimuth: float, height: float = 1.0) -> np.ndarray:
    """OpenGL camera-to-world (x right, y up, z back) at ``RADIUS`` looking at the origin."""
    eye = np.array([RADIUS * math.cos(azimuth), RADIUS * math.sin(azimuth), height])
    back = eye / np.linalg.norm(eye)
    right = np.cross([0.0, 0.0, 1.0], back)
    right /= np.linalg.norm(right)
    up = np.cross(back, right)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, up, back, eye
    return c2w


OBJECT = (slice(2, 6), slice(3, 7))
"""The opaque pixels of every frame (an object in the middle); the rest is transparent."""
CLEAR = np.ones((H, W), dtype=bool)
CLEAR[OBJECT] = False


def _rgba(index: int) -> np.ndarray:
    """[H, W, 4]: an opaque object with a colour of its own on a transparent background."""
    rgba = np.zeros((H, W, 4), dtype=np.uint8)
    rgba[..., :3] = (10, 250, 10)  # what a transparent pixel stores must never show
    rgba[OBJECT] = (200, 20 * index, 100, 255)
    return rgba


def blender_folder(root: Path, timed: bool = False, rgb_on: tuple[int, int, int] | None = None) -> Path:
    """A Blender-layout folder: train/val/test frames at azimuths spread on a ring, extension-less
    file paths, RGBA PNGs (or RGB on the colour ``rgb_on`` when given), D-NeRF times when ``timed``."""
    root.mkdir(parents=True)
    n = sum(SPLITS.values())
    k = 0
    for split, count in SPLITS.items():
        (root / split).mkdir()
        frames = []
        for i in range(count):
            rgba = _rgba(k)
            if rgb_on is None:
                Image.fromarray(rgba, "RGBA").save(root / split / f"r_{i:03d}.png")
            else:
                a = rgba[..., 3:4].astype(np.float64) / 255.0
                rgb = np.round(rgba[..., :3] * a + np.asarray(rgb_on) * (1 - a)).astype(np.uint8)
                Image.fromarray(rgb, "RGB").save(root / split / f"r_{i:03d}.png")
            frame = {"file_path": f"./{split}/r_{i:03d}", "transform_matrix": _c2w_gl(2 * math.pi * k / n).tolist()}
            if timed:
                frame["time"] = round(k / (n - 1), 4)
            frames.append(frame)
            k += 1
        (root / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": ANGLE, "frames": frames}))
    return root


def _edit(path: Path, change) -> None:
    meta = json.loads(path.read_text())
    change(meta)
    path.write_text(json.dumps(meta))


def _dm(root: Path, tmp_path: Path, **kwargs):
    return DataManagerConfig(data=str(root), n_random_points=64, cache_dir=str(tmp_path / "cache"), **kwargs).setup()


def _times(root: Path, split: str) -> list[float]:
    return [f["time"] for f in json.loads((root / f"transforms_{split}.json").read_text())["frames"]]


# ---- loading, splits, backgrounds ----

def test_train_for_training_test_for_evaluation_white_by_default(tmp_path: Path) -> None:
    root = blender_folder(tmp_path / "lego")
    dm = _dm(root, tmp_path)
    assert [c.name for c in dm.train_cameras] == [f"train/r_{i:03d}.png" for i in range(4)]
    assert [c.name for c in dm.test_cameras] == [f"test/r_{i:03d}.png" for i in range(3)]
    assert dm.parsed.layout == "blender" and not dm.is_dynamic
    assert all(c.time is None for c in dm.train_cameras + dm.test_cameras)
    assert dm.background.tolist() == [1.0, 1.0, 1.0] and not dm.random_background
    camera, image, extras = dm.train_item(1)
    np.testing.assert_allclose(camera.K.numpy(), [[10, 0, 5], [0, 10, 4], [0, 0, 1]], atol=1e-6)
    assert image.shape == (H, W, 3) and extras["alpha"].shape == (H, W, 1)
    assert torch.equal(extras["alpha"][..., 0], torch.from_numpy(~CLEAR).float())
    # the object: the frame's own colour; transparent pixels: white, never the stored green
    assert torch.allclose(image[3, 4], torch.tensor([200, 20, 100]) / 255.0)
    assert torch.equal(image[CLEAR], torch.ones(int(CLEAR.sum()), 3))
    _, test_image, _ = dm.test_item(0)
    assert torch.equal(test_image[CLEAR], torch.ones(int(CLEAR.sum()), 3))  # evaluation on white too


@pytest.mark.parametrize(("option", "expected"), [("black", [0.0, 0.0, 0.0]), ((0.0, 0.0, 1.0), [0.0, 0.0, 1.0])])
def test_named_and_explicit_backgrounds(tmp_path: Path, option, expected) -> None:
    dm = _dm(blender_folder(tmp_path / "lego"), tmp_path, background=option)
    assert dm.background.tolist() == expected
    _, image, _ = dm.train_item(0)
    assert torch.equal(image[3, W - 1], torch.tensor(expected, dtype=torch.float32))


def test_random_background_recomposites_each_training_view(tmp_path: Path) -> None:
    """--datamanager.background random: the pipeline puts every training view on a random colour
    (target = c a + b (1 - a)) and renders on the same colour; evaluation stays on white."""
    from exploregs_plugin.engine.pipeline import Pipeline, PipelineConfig
    from exploregs_plugin.schedule import ScheduleConfig

    root = blender_folder(tmp_path / "lego")
    dm_config = DataManagerConfig(data=str(root), background="random", n_random_points=64,
                                  cache_dir=str(tmp_path / "cache"))
    pipeline = Pipeline(PipelineConfig(datamanager=dm_config), ScheduleConfig().resolve(10), seed=0)
    assert pipeline.random_background and pipeline.datamanager.background.tolist() == [1.0, 1.0, 1.0]
    seen = []
    real_render = pipeline.model.render

    def spy(camera, sh_degree, background):
        seen.append(background.clone())
        return real_render(camera, sh_degree, background)

    pipeline.model.render = spy
    pipeline.train_step(0)
    pipeline.train_step(1)
    assert len(seen) == 2 and not torch.allclose(seen[0], seen[1])
    assert all(not torch.allclose(b, torch.ones(3)) for b in seen)


def test_val_is_selectable_for_evaluation(tmp_path: Path) -> None:
    root = blender_folder(tmp_path / "lego", timed=True)
    dm = _dm(root, tmp_path, eval_split="val")
    assert [c.name for c in dm.test_cameras] == ["val/r_000.png", "val/r_001.png"]
    assert [c.time for c in dm.test_cameras] == pytest.approx(_times(root, "val"))
    assert len(dm.train_cameras) == 4


def test_val_refused_outside_the_blender_layout(tmp_path: Path) -> None:
    root = blender_folder(tmp_path / "lego")
    scene = read_transforms(root, ParseOptions())
    single = write_transforms(scene, tmp_path / "flat" / "transforms.json")
    with pytest.raises(DataError, match=r"^--datamanager\.eval-split: val needs a Blender folder"):
        _dm(single, tmp_path, eval_split="val")


def test_tyro_flags_name_the_background(tmp_path: Path) -> None:
    def parse(*args: str) -> DataManagerConfig:
        # nested as eg-train nests it (at the top level its --data alias would be its own name)
        flags = [f"--datamanager.{a[2:]}" if a.startswith("--") else a for a in args]
        return tyro.cli(PipelineConfig, args=flags).datamanager

    assert parse("--background", "white").background == "white"
    assert parse("--background", "random").background == "random"
    assert parse("--background", "1", "0.5", "0").background == (1.0, 0.5, 0.0)
    assert parse().background is None
    assert parse("--eval-split", "val").eval_split == "val"


# ---- images without alpha ----

def test_rgb_on_black_keeps_black_and_says_so(tmp_path: Path, capsys) -> None:
    root = blender_folder(tmp_path / "lego", rgb_on=(0, 0, 0))
    dm = _dm(root, tmp_path)
    out = capsys.readouterr().out.strip().splitlines()
    assert len(out) == 1 and out[0].startswith(f"note: {root}: the images have no alpha channel")
    assert "evidently black" in out[0] and out[0].endswith("so renders use black")
    assert dm.background.tolist() == [0.0, 0.0, 0.0] and not dm.has_alpha
    _, image, extras = dm.train_item(0)
    assert "alpha" not in extras and torch.equal(image[CLEAR], torch.zeros(int(CLEAR.sum()), 3))


def test_rgb_without_alpha_and_an_explicit_background(tmp_path: Path, capsys) -> None:
    root = blender_folder(tmp_path / "lego", rgb_on=(0, 0, 0))
    dm = _dm(root, tmp_path, background="white")
    out = capsys.readouterr().out
    assert "evidently black" in out and "renders use 1 1 1 as --datamanager.background says" in out
    assert dm.background.tolist() == [1.0, 1.0, 1.0]


def test_rgb_on_no_one_colour_keeps_the_layout_default(tmp_path: Path, capsys) -> None:
    root = blender_folder(tmp_path / "lego", rgb_on=(90, 60, 30))
    dm = _dm(root, tmp_path)
    assert "their borders have no one colour" in capsys.readouterr().out
    assert dm.background.tolist() == [1.0, 1.0, 1.0]


def test_random_background_without_alpha_names_the_image(tmp_path: Path) -> None:
    root = blender_folder(tmp_path / "lego", rgb_on=(0, 0, 0))
    with pytest.raises(DataError, match=r"train/r_000\.png: --datamanager\.background random needs images with an "
                                        r"alpha channel, and this one has none$"):
        _dm(root, tmp_path, background="random")


def test_evident_background_from_the_border() -> None:
    black = np.zeros((6, 5, 3), np.uint8)
    black[2:4, 2:3] = 255  # the object in the middle does not count
    assert evident_background([black]) == ("black", {"white": 0.0, "black": 1.0})
    white = np.full((6, 5, 3), 250, np.uint8)  # within the tolerance of white
    white[0, 0] = 0
    name, shares = evident_background([white])
    assert name == "white" and shares["white"] == pytest.approx(17 / 18)  # 2 (6 + 5) - 4 = 18 border pixels
    grey = np.full((6, 5, 3), 128, np.uint8)
    assert evident_background([grey, black]) == (None, {"white": 0.0, "black": 0.5})
    assert border_shares([np.zeros((1, 1, 3), np.uint8)]) == {"white": 0.0, "black": 1.0}


# ---- time (D-NeRF) ----

def test_times_reach_every_camera(tmp_path: Path) -> None:
    root = blender_folder(tmp_path / "dnerf", timed=True)
    dm = _dm(root, tmp_path)
    assert dm.is_dynamic
    assert [c.time for c in dm.train_cameras] == pytest.approx(_times(root, "train"))
    assert [c.time for c in dm.test_cameras] == pytest.approx(_times(root, "test"))
    # a written copy keeps them
    copy = read_transforms(write_transforms(dm.parsed, tmp_path / "copy" / "transforms.json"), ParseOptions())
    assert [im.time for im in copy.images] == [im.time for im in dm.parsed.images]


def test_dynamic_method_trains_and_evaluates_each_test_camera_at_its_time(tmp_path: Path) -> None:
    from exploregs_plugin.evaluation.metrics import evaluate
    from exploregs_plugin.method_configs import get_method
    from exploregs_plugin.schedule import ScheduleConfig

    root = blender_folder(tmp_path / "dnerf", timed=True)
    config = get_method("exploregs-4d-default").config
    pipeline = replace(config.pipeline, datamanager=replace(
        config.pipeline.datamanager, data=str(root), n_random_points=64, cache_dir=str(tmp_path / "cache")))
    config = replace(config, pipeline=pipeline, max_steps=20, run_dir=tmp_path / "run", quiet=True, tensorboard=False,
                     eval_count=1, save_eval_images=False, schedule=ScheduleConfig(min_refine_every=10))
    trainer = config.setup()
    model, dm = trainer.pipeline.model, trainer.pipeline.datamanager
    trained_at = []
    real_params_at = model.params_at

    def spy(time):
        trained_at.append(time)
        return real_params_at(time)

    model.params_at = spy
    metrics = trainer.train()
    assert bool(model.deformation.active)
    assert set(trained_at[:20]) == set(_times(root, "train"))  # each view at its own time
    assert [f["time"] for f in metrics["per_image"]] == pytest.approx(_times(root, "test"))
    trained_at.clear()
    evaluate(model, dm)
    assert trained_at == pytest.approx(_times(root, "test"))


def test_static_method_says_once_that_time_is_ignored(tmp_path: Path, capsys) -> None:
    from exploregs_plugin.engine.pipeline import PipelineConfig
    from exploregs_plugin.schedule import ScheduleConfig

    root = blender_folder(tmp_path / "dnerf", timed=True)
    PipelineConfig(datamanager=DataManagerConfig(data=str(root), n_random_points=64, cache_dir=str(tmp_path / "c"))
                   ).setup(ScheduleConfig().resolve(10), seed=0)
    lines = [ln for ln in capsys.readouterr().out.splitlines() if "time" in ln]
    assert lines == ["note: dnerf: the frames carry times (a dynamic scene), which this static method ignores: it "
                     "trains every frame as one still scene (the exploregs-4d-* methods use them)"]
    PipelineConfig(datamanager=DataManagerConfig(data=str(blender_folder(tmp_path / "still")), n_random_points=64,
                                                 cache_dir=str(tmp_path / "c"))).setup(ScheduleConfig().resolve(10), seed=0)
    assert "time" not in capsys.readouterr().out


# ---- initialisation without points ----

def test_cube_around_the_focus_point_seen_by_every_view(tmp_path: Path) -> None:
    root = blender_folder(tmp_path / "lego")
    scene = read_transforms(root, ParseOptions())  # file units: cameras at distance sqrt(4^2 + 1) from the origin
    centre, half = cube_bounds(scene.images)
    np.testing.assert_allclose(centre, 0.0, atol=1e-9)  # every camera looks at the origin
    assert half == pytest.approx(math.sqrt(RADIUS ** 2 + 1) * (H / 2) / 10)  # narrower view: h / 2 / fy
    points, rgb = cube_points(scene.images, 500, seed=3)
    assert points.shape == (500, 3) and rgb.shape == (500, 3)
    assert np.all(np.abs(points) <= half) and np.abs(points).max() > 0.9 * half  # filled to the faces
    np.testing.assert_array_equal(cube_points(scene.images, 500, seed=3)[0], points)


def test_blender_folder_starts_from_the_cube_others_from_frusta(tmp_path: Path) -> None:
    root = blender_folder(tmp_path / "lego")
    dm = _dm(root, tmp_path, seed=5)
    train_records = [im for im in dm.parsed.images if im.name.startswith("train/")]
    centre, half = cube_bounds(train_records)
    assert dm.points.shape == (64, 3)
    assert np.all(np.abs(dm.points.numpy() - centre) <= half + 1e-6)
    frusta = _dm(root, tmp_path, seed=5, random_init_mode="frusta")
    assert not torch.equal(frusta.points, dm.points)


# ---- bad input: one line naming the file ----

def test_missing_split_file(tmp_path: Path) -> None:
    root = blender_folder(tmp_path / "lego")
    (root / "transforms_test.json").unlink()
    with pytest.raises(DataError, match=r"transforms_test\.json: split file does not exist; a Blender folder needs "
                                        r"it for evaluation \(--datamanager\.eval-split test\)$"):
        _dm(root, tmp_path)
    (root / "transforms_val.json").unlink()
    with pytest.raises(DataError, match=r"transforms_val\.json: split file does not exist"):
        _dm(root, tmp_path, eval_split="val")


def test_frame_without_time_among_timed_ones(tmp_path: Path) -> None:
    root = blender_folder(tmp_path / "dnerf", timed=True)
    _edit(root / "transforms_test.json", lambda m: m["frames"][1].pop("time"))
    with pytest.raises(DataError, match=r"transforms_test\.json \(frame 1\): has no 'time', though other frames have "
                                        r"one \(.*transforms_train\.json \(frame 0\)\)"):
        _dm(root, tmp_path)


def test_time_outside_zero_one(tmp_path: Path) -> None:
    root = blender_folder(tmp_path / "dnerf", timed=True)
    _edit(root / "transforms_train.json", lambda m: m["frames"][2].__setitem__("time", 1.5))
    with pytest.raises(DataError, match=r"transforms_train\.json \(frame 2\): 'time' must be in \[0, 1\]"):
        _dm(root, tmp_path)


@pytest.mark.parametrize(("file_path", "tail"), [("./train/r_009", " nor with .png (or .jpg)"),
                                                 ("./train/r_009.png", "")])
def test_file_path_that_does_not_exist(tmp_path: Path, file_path: str, tail: str) -> None:
    root = blender_folder(tmp_path / "lego")
    _edit(root / "transforms_train.json", lambda m: m["frames"][3].__setitem__("file_path", file_path))
    expected = (f"{root / 'transforms_train.json'} (frame 3): file_path '{file_path}' names no image: "
                f"{root / file_path} does not exist{tail}")
    with pytest.raises(DataError) as err:
        _dm(root, tmp_path)
    assert str(err.value) == expected


def test_images_of_different_sizes(tmp_path: Path) -> None:
    root = blender_folder(tmp_path / "lego")
    Image.fromarray(np.zeros((H * 2, W * 2, 4), np.uint8), "RGBA").save(root / "test" / "r_001.png")
    with pytest.raises(DataError) as err:
        _dm(root, tmp_path)
    assert str(err.value) == (f"{root / 'test' / 'r_001.png'}: image is 20x16 but {root / 'train' / 'r_000.png'} "
                              "is 10x8: the frames of a Blender dataset share one camera, so their images must have "
                              "one size")


def test_generated_rgba_objects_scene_loads_with_soft_alpha(tmp_path: Path) -> None:
    from exploregs_plugin.data.builtin.blender_objects import write_blender_objects

    root = write_blender_objects(tmp_path / "objects", size=24, seed=0, splits=(("train", 3), ("test", 2)))
    dm = _dm(root, tmp_path)
    assert (len(dm.train_cameras), len(dm.test_cameras)) == (3, 2) and dm.has_alpha
    assert dm.train_cameras[0].K[0, 0].item() == pytest.approx(12 / math.tan(math.radians(39.6) / 2), rel=1e-6)
    alphas = torch.stack([dm.train_item(i)[2]["alpha"] for i in range(3)])
    assert float(alphas.max()) == 1.0 and float(alphas.min()) == 0.0
    assert bool(((alphas > 0) & (alphas < 1)).any())  # anti-aliased silhouettes: coverage of the sub-samples
    _, image, extras = dm.train_item(0)
    clear = extras["alpha"][..., 0] == 0
    assert torch.equal(image[clear], torch.ones(int(clear.sum()), 3))  # empty pixels on white
    scene = read_transforms(root, ParseOptions())  # file units: every camera 4 from the objects' centre
    for im in scene.images:
        assert np.linalg.norm(im.camera_center - [0.0, 0.0, 0.4]) == pytest.approx(4.0, abs=1e-9)
        forward = im.viewmat[2, :3]  # looking at it
        to_centre = np.array([0.0, 0.0, 0.4]) - im.camera_center
        np.testing.assert_allclose(forward, to_centre / 4.0, atol=1e-9)
