"""The DataParser result: what every dataset format is turned into.

A parser reads a dataset in its own conventions and returns a :class:`ParsedScene` in ours:
OpenCV camera axes (x right, y down, z forward), world-to-camera ``viewmat [4, 4]``, pinhole
``K [3, 3]`` with pixel centres at +0.5, all numpy float64 so reference tests can run in
double precision. Images stay on disk (paths); the DataManager loads them.

Scene normalisation (translation and one uniform scale, never a rotation, so spherical
harmonics never need rotating)::

    c = mean_i C_i                        # C_i: camera centres in the file's world frame
    r = max_i |C_i - c|                   # camera-centre radius (1 when r <= 1e-12)
    translation = -c,  scale = 1 / r
    x_norm = (x_orig + translation) * scale          # points, camera centres
    x_orig = x_norm / scale - translation            # the inverse, for exports

A world-to-camera pose ``[R | t]`` becomes ``[R | scale * (t - R @ translation)]`` (the camera
frame is scaled by the same factor, which leaves every projection unchanged), and depths
measured in the file's units are multiplied by ``scale``.

``scene_extent`` is computed as 3DGS does: 1.1 times the largest distance of a camera centre
from the mean camera centre, measured after normalisation.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from .cache import cache_root

BLENDER_LAYOUT = "blender"
"""``ParsedScene.layout`` of a folder of ``transforms_{train,val,test}.json`` (NeRF-synthetic, D-NeRF)."""

EXTENT_MARGIN = 1.1
"""3DGS enlarges the camera-centre radius by 10% to get the scene extent."""

MIN_RADIUS = 1e-12
"""Below this camera-centre radius (one camera, or all at one spot) the scale stays 1."""

REGION_LABELS = {"other": 0, "far": 1, "occluded": 2, "moving": 3}
"""Values in a region-mask PNG (``masks/<stem>.png``): one label per pixel. In a dynamic scene
``occluded`` is static content that moving things cover part of the time (occluded by motion)
and ``moving`` the moving things themselves; static scenes have no ``moving`` pixels."""


@dataclass(frozen=True)
class Normalization:
    """``x_norm = (x_orig + translation) * scale``; translation: [3], scale > 0."""

    translation: np.ndarray
    scale: float

    @staticmethod
    def identity() -> "Normalization":
        return Normalization(np.zeros(3), 1.0)

    def apply_points(self, points: np.ndarray) -> np.ndarray:
        """points: [..., 3] in file units -> normalised [..., 3]."""
        return (points + self.translation) * self.scale

    def invert_points(self, points: np.ndarray) -> np.ndarray:
        """points: [..., 3] normalised -> file units [..., 3]."""
        return points / self.scale - self.translation

    def apply_viewmat(self, viewmat: np.ndarray) -> np.ndarray:
        """viewmat: [4, 4] world-to-camera in file units -> the same camera in normalised units."""
        out = np.array(viewmat, dtype=np.float64, copy=True)
        rot = out[:3, :3]
        out[:3, 3] = self.scale * (out[:3, 3] - rot @ self.translation)
        return out

    def invert_viewmat(self, viewmat: np.ndarray) -> np.ndarray:
        """viewmat: [4, 4] normalised world-to-camera -> the same camera in file units."""
        out = np.array(viewmat, dtype=np.float64, copy=True)
        rot = out[:3, :3]
        out[:3, 3] = out[:3, 3] / self.scale + rot @ self.translation
        return out


@dataclass
class ImageRecord:
    """One image of a dataset.

    K: [3, 3] float64 for an image of ``width`` x ``height``.
    viewmat: [4, 4] float64 world-to-camera, OpenCV axes.
    depth_path: ``.npy`` float32 [H, W] camera-space z in the file's units (0 = no depth).
    mask_path: PNG region labels (see :data:`REGION_LABELS`).
    """

    name: str
    path: Path
    width: int
    height: int
    K: np.ndarray
    viewmat: np.ndarray
    depth_path: Path | None = None
    mask_path: Path | None = None
    time: float | None = None
    """The frame's time in [0, 1] in a dynamic scene (None: a static scene)."""
    pixel_kind: str = "rgb"
    """How the file's pixels become RGB: rgb, gray, gray16 or alpha (see ``images.pixel_kind``)."""

    @property
    def camera_center(self) -> np.ndarray:
        """[3] = -R^T t."""
        return -self.viewmat[:3, :3].T @ self.viewmat[:3, 3]


@dataclass
class ParsedScene:
    """What a DataParser returns (normalised world frame unless ``normalization`` is identity).

    points: [P, 3] float64 or None; points_rgb: [P, 3] float64 in [0, 1] or None.
    split: the dataset's own ``{"train": [names], "test": [names]}`` when it has one.
    background: [3] colour the parser chose for transparent pixels (the option's, or its layout's
    convention); None: the datamanager's option, else black.
    """

    name: str
    root: Path
    images: list[ImageRecord]
    points: np.ndarray | None
    points_rgb: np.ndarray | None
    normalization: Normalization = field(default_factory=Normalization.identity)
    scene_extent: float = 1.0
    split: dict[str, list[str]] | None = None
    background: np.ndarray | None = None
    depth_scale: float = 1.0
    """Multiply stored depth values by this to get normalised depths (= normalisation scale)."""
    layout: str | None = None
    """A layout whose conventions the datamanager follows: ``"blender"`` (NeRF-synthetic, D-NeRF:
    a white background, random initial points in a cube around the object); None: none."""


@dataclass(frozen=True)
class ParseOptions:
    """What every parser needs besides the dataset path (built from the DataManagerConfig)."""

    data_factor: int = 1
    undistort: bool = True
    cache_root: Path = field(default_factory=cache_root)
    """Root of the cache: derived images (resized, undistorted, decoded frames) and built-in scenes."""
    cache_beside_data: bool = False
    """Keep derived images in the dataset's own ``.exploregs/`` folder (when writable) instead."""
    background: np.ndarray | None = None
    frame_stride: int = 1
    """Dynamic scenes: keep every this-many-th frame of each camera."""
    max_frames: int | None = None
    """Dynamic scenes: keep frames of the first this-many of each camera's clip (None: all)."""
    eval_split: str = "test"
    """Blender layout: the evaluated split's file, ``transforms_test.json`` or ``transforms_val.json``."""


def camera_centers(images: list[ImageRecord]) -> np.ndarray:
    """[N, 3] camera centres of ``images``."""
    return np.stack([im.camera_center for im in images]) if images else np.zeros((0, 3))


def compute_normalization(centers: np.ndarray) -> Normalization:
    """The translation + uniform scale that puts the camera centres at mean 0, max radius 1.

    centers: [N, 3] camera centres (N >= 1).
    """
    center = centers.mean(axis=0)
    radius = float(np.linalg.norm(centers - center, axis=1).max())
    scale = 1.0 / radius if radius > MIN_RADIUS else 1.0
    return Normalization(-center, scale)


def scene_extent(centers: np.ndarray) -> float:
    """3DGS scene extent: 1.1 x max distance of a camera centre from their mean. centers: [N, 3]."""
    radius = float(np.linalg.norm(centers - centers.mean(axis=0), axis=1).max())
    # One camera (radius 0) would give a zero extent, which zeroes learning rates: use 1.
    return EXTENT_MARGIN * radius if radius > MIN_RADIUS else 1.0


def normalize_scene(scene: ParsedScene, enabled: bool = True) -> ParsedScene:
    """Return ``scene`` in the normalised frame (or with identity normalisation) and its extent.

    ``scene`` must be in file units (identity normalisation).
    """
    centers = camera_centers(scene.images)
    norm = compute_normalization(centers) if enabled else Normalization.identity()
    images = [replace(im, viewmat=norm.apply_viewmat(im.viewmat)) for im in scene.images]
    points = norm.apply_points(scene.points) if scene.points is not None else None
    return replace(
        scene,
        images=images,
        points=points,
        normalization=norm,
        scene_extent=scene_extent(norm.apply_points(centers)),
        depth_scale=norm.scale,
    )
