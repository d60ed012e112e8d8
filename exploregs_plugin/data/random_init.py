"""Random initial points for datasets without a point cloud.

- ``frustum_points``: along the rays of random training pixels, at log-uniform depths between a
  near and a far bound, coloured by those pixels. Every point lies in front of a training camera
  and has the colour that camera saw there, wherever the content is (inside the ring of
  cameras, or far beyond it for an outward-looking capture).
- ``box_points``: uniform in the box spanned by the camera centres and the focus point (the
  point closest, in least squares, to every optical axis: where the cameras look), padded by 10%
  of its largest side, with random colours. Content outside that box is out of reach.
- ``cube_points``: the 3DGS recipe for synthetic object scenes (NeRF-synthetic, D-NeRF), uniform
  in a cube around the object with random colours. 3DGS hard-codes [-1.3, 1.3]^3 for Blender's
  cameras at radius 4 with a 40 degree field of view; here the cube is centred on the focus point
  and its half side is the smallest half-width of a view at the focus point, min_i d_i tan(fov_i / 2)
  (d_i: camera i's distance to the focus point, fov_i: its narrower field of view): the largest
  cube whose middle slice every camera sees whole. On Blender's cameras that is 4.03 x tan(20 deg)
  = 1.45, near 3DGS's 1.3, in any units and wherever the object stands.
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


def box_points(images: list[ImageRecord], count: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """``count`` uniform points [count, 3] in the camera box and random colours [count, 3]."""
    centers = np.stack([im.camera_center for im in images])
    forwards = np.stack([im.viewmat[2, :3] for im in images])  # camera z axis in world = row 2 of R
    corners = np.concatenate([centers, focus_point(centers, forwards)[None]], axis=0)
    lo, hi = corners.min(axis=0), corners.max(axis=0)
    pad = 0.1 * max(float((hi - lo).max()), 1e-3)
    rng = np.random.default_rng([seed, 7])
    points = rng.uniform(lo - pad, hi + pad, size=(count, 3))
    return points, rng.random((count, 3))


def frustum_points(
    views: list[tuple[np.ndarray, np.ndarray, np.ndarray]], count: int, near: float, far: float, seed: int
) -> tuple[np.ndarray, np.ndarray]:
    """``count`` points [count, 3] on the rays of random pixels of random views, at camera depth
    z log-uniform in [near, far], and their pixels' colours [count, 3] in [0, 1].

    views: (viewmat [4, 4] world-to-camera, K [3, 3], image [H, W, 3] uint8) per training view.
    A pixel centre (u, v) at depth z is X_cam = z K^-1 (u, v, 1); X = R^T (X_cam - t).
    """
    if not views:
        raise ValueError("frustum initialisation needs at least one training view")
    if not 0.0 < near < far:
        raise ValueError(f"frustum initialisation needs 0 < near < far, got {near}, {far}")
    rng = np.random.default_rng([seed, 11])
    which = rng.integers(len(views), size=count)
    points = np.empty((count, 3))
    rgb = np.empty((count, 3))
    depth = np.exp(rng.uniform(np.log(near), np.log(far), size=count))
    for v in np.unique(which):
        viewmat, K, image = views[v]
        rows = np.flatnonzero(which == v)
        h, w = image.shape[:2]
        px = rng.integers(w, size=len(rows))
        py = rng.integers(h, size=len(rows))
        pix = np.stack([px + 0.5, py + 0.5, np.ones(len(rows))], axis=1)
        cam = (np.linalg.inv(np.asarray(K, dtype=np.float64)) @ pix.T).T * depth[rows, None]
        rot, trans = np.asarray(viewmat, dtype=np.float64)[:3, :3], np.asarray(viewmat, dtype=np.float64)[:3, 3]
        points[rows] = (cam - trans) @ rot  # R^T (x - t), row-wise
        rgb[rows] = image[py, px, :3] / 255.0
    return points, rgb


def cube_bounds(images: list[ImageRecord]) -> tuple[np.ndarray, float]:
    """(centre [3], half side) of the initialisation cube of :func:`cube_points`: the cameras'
    focus point and min_i |C_i - focus| tan(fov_i / 2) over the narrower field of view."""
    centers = np.stack([im.camera_center for im in images])
    forwards = np.stack([im.viewmat[2, :3] for im in images])
    focus = focus_point(centers, forwards)
    # tan of half the narrower field of view: (w / 2) / fx or (h / 2) / fy, whichever is smaller
    tan_half = np.array([min(0.5 * im.width / im.K[0, 0], 0.5 * im.height / im.K[1, 1]) for im in images])
    half = float(np.min(np.linalg.norm(centers - focus, axis=1) * tan_half))
    return focus, max(half, 1e-6)


def cube_points(images: list[ImageRecord], count: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """``count`` uniform points [count, 3] in the cube of :func:`cube_bounds` and random colours [count, 3]."""
    centre, half = cube_bounds(images)
    rng = np.random.default_rng([seed, 13])
    points = rng.uniform(centre - half, centre + half, size=(count, 3))
    return points, rng.random((count, 3))
