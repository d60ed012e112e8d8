"""Built-in scenes: round trip through COLMAP text, ground truth alignment, determinism, cache."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from exploregs_plugin.data import DataError, ParseOptions, read_colmap
from exploregs_plugin.data.builtin.presets import PRESETS, ensure_builtin, generate, make_scene
from exploregs_plugin.data.parsed import REGION_LABELS, normalize_scene
from exploregs_plugin.data.builtin.raycast import pixel_rays, trace
from exploregs_plugin.data.builtin.layouts import build_world, camera_path, view_kinds

TINY = PRESETS["tiny"]
SMALL = replace(TINY, width=32, height=24, n_views=6, n_points=100)


@pytest.fixture(scope="module")
def tiny_generated():
    """The tiny preset regenerated in memory (same seed as the cached folder)."""
    return generate(TINY)


def _project(K: np.ndarray, viewmat: np.ndarray, points: np.ndarray) -> np.ndarray:
    cam = points @ viewmat[:3, :3].T + viewmat[:3, 3]
    return (cam[:, :2] / cam[:, 2:3]) @ K[:2, :2].T + K[:2, 2]


def test_written_scene_reads_back_same_cameras_and_points(tiny_scene_dir: Path, tiny_generated) -> None:
    scene = read_colmap(tiny_scene_dir, ParseOptions())
    gen = tiny_generated
    assert [im.name for im in scene.images] == gen.names
    for im, K, c2w in zip(scene.images, gen.Ks, gen.c2ws):
        assert (im.width, im.height) == (TINY.width, TINY.height)
        np.testing.assert_allclose(im.K, K, atol=1e-12)
        np.testing.assert_allclose(im.viewmat, np.linalg.inv(c2w), atol=1e-12)
        assert im.depth_path is not None and im.mask_path is not None
    np.testing.assert_allclose(scene.points, gen.points, rtol=0, atol=1e-12)
    np.testing.assert_allclose(scene.points_rgb, np.round(gen.points_rgb * 255) / 255, atol=1e-12)
    assert scene.split == {"train": gen.train, "test": gen.test}


def test_pixels_reproject_within_1e6_px_in_float64(tiny_scene_dir: Path, tiny_generated) -> None:
    """Rays cast through pixel centres hit points that the loaded cameras project back onto the
    same pixel centres, before and after normalisation."""
    raw = read_colmap(tiny_scene_dir, ParseOptions())
    norm = normalize_scene(raw)
    prims = build_world(TINY.layout, TINY.seed)
    for index in (0, 3, 7):
        K, c2w = tiny_generated.Ks[index], tiny_generated.c2ws[index]
        origin, dirs, _ = pixel_rays(K, c2w, TINY.width, TINY.height, 1)
        hits = trace(origin, dirs, prims)
        points = origin + hits.t[:, None] * dirs
        u, v = np.meshgrid(np.arange(TINY.width) + 0.5, np.arange(TINY.height) + 0.5)
        expected = np.stack([u.ravel(), v.ravel()], axis=1)
        im = raw.images[index]
        assert np.abs(_project(im.K, im.viewmat, points) - expected).max() < 1e-6
        im_n = norm.images[index]
        moved = norm.normalization.apply_points(points)
        assert np.abs(_project(im_n.K, im_n.viewmat, moved) - expected).max() < 1e-6


def test_depths_and_masks_align_with_images(tiny_dm, tiny_generated) -> None:
    gen = tiny_generated
    scale = tiny_dm.normalization[1]
    for i, name in enumerate(gen.test):
        cam, image, extras = tiny_dm.test_item(i)
        index = gen.names.index(name)
        assert image.shape == (cam.height, cam.width, 3)
        depth = extras["depth"][..., 0].numpy()
        assert extras["depth"].shape == (cam.height, cam.width, 1)
        np.testing.assert_allclose(depth, gen.depths[index] * scale, rtol=1e-6)
        stored = np.asarray(Image.open(Path(tiny_dm.parsed.root) / "images" / name), dtype=np.float64) / 255
        np.testing.assert_allclose(image.numpy(), stored, atol=1e-6)
        masks = extras["masks"]
        assert set(masks) == set(REGION_LABELS) - {"moving"}  # a static scene: nothing moves
        stack = np.stack([m.numpy() for m in masks.values()])
        assert stack.shape == (3, cam.height, cam.width)
        assert (stack.sum(axis=0) == 1).all(), "regions must partition the image"
        # far pixels are the distant ones: in file units depth > far_radius - camera distance
        cam_dist = np.linalg.norm(gen.c2ws[index][:3, 3])
        far_depth_file = depth[masks["far"].numpy()] / scale
        assert far_depth_file.min() > TINY.far_radius - cam_dist - 1e-6
        near_depth_file = depth[~masks["far"].numpy()] / scale
        assert near_depth_file.max() < TINY.far_radius + cam_dist
        # both traps are present in the tiny test view
        assert masks["far"].float().mean() > 0.15
        assert masks["occluded"].float().mean() > 0.05


def test_depth_is_camera_z_of_the_surface(tiny_generated) -> None:
    """Unprojecting a pixel centre with its depth lands on the hit of the centre ray."""
    gen = tiny_generated
    prims = build_world(TINY.layout, TINY.seed)
    K, c2w, depth = gen.Ks[2], gen.c2ws[2], gen.depths[2]
    origin, dirs, _ = pixel_rays(K, c2w, TINY.width, TINY.height, 1)
    hits = trace(origin, dirs, prims)
    u, v = np.meshgrid(np.arange(TINY.width) + 0.5, np.arange(TINY.height) + 0.5)
    cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1) * depth[..., None]
    world = cam.reshape(-1, 3) @ c2w[:3, :3].T + c2w[:3, 3]
    expected = origin + hits.t[:, None] * dirs
    np.testing.assert_allclose(world, expected, rtol=1e-9, atol=1e-9 * np.abs(expected).max())


def test_generator_is_deterministic_and_seed_dependent() -> None:
    a, b = generate(SMALL), generate(SMALL)
    for field in ("images", "depths", "labels", "points", "points_rgb", "c2ws"):
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
    c = generate(replace(SMALL, seed=5))
    assert np.abs(a.images - c.images).mean() > 0.01
    assert np.abs(a.c2ws - c.c2ws).max() > 1e-3
    assert a.points.shape == c.points.shape and not np.allclose(a.points, c.points)


def test_sparse_points_are_sfm_like(tiny_generated) -> None:
    """Points lie on surfaces seen by training views; far content gets few of them."""
    gen = tiny_generated
    assert gen.points.shape == (TINY.n_points, 3)
    assert np.all(np.isfinite(gen.points)) and gen.points_rgb.min() >= 0 and gen.points_rgb.max() <= 1
    far_points = np.linalg.norm(gen.points, axis=1) > TINY.far_radius
    far_pixels = np.mean(gen.labels == REGION_LABELS["far"])
    assert 0 < far_points.mean() < 0.5 * far_pixels
    assert gen.points[~far_points, 2].min() > -0.05  # nothing below the ground (noise aside)


def test_layouts_trap_design() -> None:
    """Far-side cameras move little relative to the distant content; near-side has few clear views."""
    poses = camera_path("farside", 32, 8, 0)
    centers = np.stack([p.c2w[:3, 3] for p in poses])
    baseline = np.linalg.norm(centers.max(0) - centers.min(0))
    assert baseline < 0.1 * 60.0  # skyline radius
    kinds = view_kinds(32, 8)
    train_clear = [k for i, k in enumerate(kinds) if i % 8 != 0 and k]
    assert 1 <= len(train_clear) <= 4 and kinds[8]  # a clear test view and a few clear train views


def test_builtin_cache_is_reused_and_refreshed(tmp_path: Path) -> None:
    first = ensure_builtin("tiny", tmp_path, width=24, height=16, n_views=3, n_points=20)
    stamp = (first / "scene.json").stat().st_mtime_ns
    again = ensure_builtin("tiny", tmp_path, width=24, height=16, n_views=3, n_points=20)
    assert again == first and (first / "scene.json").stat().st_mtime_ns == stamp
    meta = json.loads((first / "scene.json").read_text())
    meta["generator_version"] = -1
    (first / "scene.json").write_text(json.dumps(meta))
    ensure_builtin("tiny", tmp_path, width=24, height=16, n_views=3, n_points=20)
    assert json.loads((first / "scene.json").read_text())["generator_version"] != -1


def test_builtin_bad_names_and_settings(tmp_path: Path) -> None:
    with pytest.raises(DataError, match="unknown built-in scene"):
        ensure_builtin("nope", tmp_path)
    with pytest.raises(DataError, match="n_views"):
        generate(replace(TINY, n_views=1))
    with pytest.raises(DataError, match="supersample"):
        generate(replace(TINY, supersample=2))
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "x").write_text("x")
    with pytest.raises(DataError, match="not empty"):
        make_scene(SMALL, tmp_path / "full")


@pytest.mark.slow
@pytest.mark.parametrize("name", ["default", "farside", "nearside", "combined"])
def test_presets_contain_their_traps(name: str) -> None:
    """Test views of far-side scenes are largely distant content with few SfM points on it;
    near-side scenes have surface seen by few training views."""
    preset = PRESETS[name]
    scene = generate(preset)
    test_ids = [scene.names.index(n) for n in scene.test]
    labels = scene.labels[test_ids]
    far_share = np.mean(labels == REGION_LABELS["far"])
    occluded_share = np.mean(labels == REGION_LABELS["occluded"])
    far_points = np.mean(np.linalg.norm(scene.points, axis=1) > preset.far_radius)
    if preset.layout in ("farside", "combined"):
        assert far_share > 0.3 and far_points < 0.25 * far_share
    if preset.layout in ("nearside", "combined"):
        assert occluded_share > 0.08
