"""The real captured scenes in ../shared/scenes load with sane cameras (skipped when absent)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pycolmap
import pytest

from exploregs_plugin.data import ParseOptions, parse_dataset
from exploregs_plugin.data.random_init import focus_point

SCENES = Path(__file__).resolve().parents[1].parent / "shared" / "scenes"
FACTOR = 8


def _scene(name: str) -> Path:
    path = SCENES / name
    if not path.is_dir():
        pytest.skip(f"{path} is not available")
    return path


def _project(K: np.ndarray, viewmat: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    cam = points @ viewmat[:3, :3].T + viewmat[:3, 3]
    return (cam[:, :2] / cam[:, 2:3]) @ K[:2, :2].T + K[:2, 2], cam[:, 2]


def test_beer_colmap_simple_radial_undistorted_reprojects(exploregs_cache: Path) -> None:
    """Every tracked SfM point projects, through the undistorted normalised camera, onto its
    observation (undistorted with the file's SIMPLE_RADIAL camera) to a fraction of a pixel."""
    root = _scene("beer")
    scene = parse_dataset(str(root), ParseOptions(data_factor=FACTOR, cache_root=exploregs_cache))
    rec = pycolmap.Reconstruction(str(root / "sparse" / "0"))
    assert len(scene.images) == 71 and scene.points.shape == (3896, 3)
    assert scene.scene_extent == pytest.approx(1.1)
    by_name = {im.name: im for im in rec.images.values()}
    errors = []
    for record in scene.images[::7]:
        assert (record.width, record.height) != (0, 0) and record.width < record.height  # portrait video
        assert exploregs_cache in record.path.parents  # the shared folder stays untouched
        image = by_name[record.name]
        camera = rec.cameras[image.camera_id]
        obs = [(p.xy, p.point3D_id) for p in image.points2D if p.has_point3D()]
        xy = np.array([o[0] for o in obs])
        xyz = np.array([rec.points3D[o[1]].xyz for o in obs])
        rays = np.asarray(camera.cam_from_img(xy))  # normalised, distortion removed
        expected = rays @ record.K[:2, :2].T + record.K[:2, 2]
        pixels, depth = _project(record.K, record.viewmat, scene.normalization.apply_points(xyz))
        assert np.all(depth > 0)
        errors.append(np.linalg.norm(pixels - expected, axis=1))
    errors = np.concatenate(errors)
    assert np.median(errors) < 0.25 and np.percentile(errors, 95) < 1.0


def test_fox_instant_ngp_transforms_cameras_are_sane(exploregs_cache: Path) -> None:
    root = _scene("fox")
    scene = parse_dataset(str(root), ParseOptions(data_factor=FACTOR, cache_root=exploregs_cache))
    assert len(scene.images) == 67 and scene.split is None
    assert scene.points is None  # no point cloud: the datamanager initialises randomly
    centers = np.stack([im.camera_center for im in scene.images])
    forwards = np.stack([im.viewmat[2, :3] for im in scene.images])
    focus = focus_point(centers, forwards)
    assert np.linalg.norm(focus) < 3.0
    for im in scene.images:
        # undistorted pinhole close to fl_x / 8, principal point near the image centre
        assert im.K[0, 0] == pytest.approx(1375.52 / FACTOR, rel=0.05)
        assert abs(im.K[0, 2] - im.width / 2) < 0.1 * im.width
        pixel, depth = _project(im.K, im.viewmat, focus[None])
        assert depth[0] > 0, "every camera looks towards the common focus point"
        assert 0 <= pixel[0, 0] < im.width and 0 <= pixel[0, 1] < im.height
