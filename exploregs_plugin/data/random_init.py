"""Random initial points inside the camera bounds, for datasets without a point cloud.

The box spans the camera centres and the focus point (the point closest, in least squares,
to every optical axis: where the cameras look), padded by 10% of its largest side.
"""

from __future__ import annotations

import numpy as np

from .parsed import ImageRecord


def focus_point(centers: np.ndarray, forwards: np.ndarray) -> np.ndarray:
    """argmin_x sum_i |(I - f_i f_i^T)(x - C_i)|^2. centers, forwards: [N, 3] -> [3].

    With (near) parallel axes the system is singular; then the point one camera-radius ahead
    of the mean centre along the mean viewing direction is used.
    """
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for c, f in zip(centers, forwards):
        proj = np.eye(3) - np.outer(f, f)
        A += proj
        b += proj @ c
    if np.linalg.cond(A) < 1e8:
        return np.linalg.solve(A, b)
    mean_f = forwards.mean(axis=0)
    mean_f = mean_f / max(np.linalg.norm(mean_f), 1e-12)
    radius = max(float(np.linalg.norm(centers - centers.mean(0), axis=1).max()), 1.0)
    return centers.mean(axis=0) + radius * mean_f


def random_points(images: list[ImageRecord], count: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """``count`` uniform points [count, 3] in the camera box and random colours [count, 3]."""
    centers = np.stack([im.camera_center for im in images])
    forwards = np.stack([im.viewmat[2, :3] for im in images])  # camera z axis in world = row 2 of R
    corners = np.concatenate([centers, focus_point(centers, forwards)[None]], axis=0)
    lo, hi = corners.min(axis=0), corners.max(axis=0)
    pad = 0.1 * max(float((hi - lo).max()), 1e-3)
    rng = np.random.default_rng([seed, 7])
    points = rng.uniform(lo - pad, hi + pad, size=(count, 3))
    return points, rng.random((count, 3))
