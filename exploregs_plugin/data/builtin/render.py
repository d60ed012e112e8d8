"""Render a built-in scene: images, ground-truth depth, region masks and SfM-like points.

Region masks (per view, at pixel centres):
  * ``far``: the surface is farther than ``far_radius`` from the scene origin (distant ground,
    skyline, ridge, sky);
  * ``occluded``: not far, and seen by fewer than ``occluded_fraction`` of the training views
    (seen = inside the view and within 2% of that view's depth at the pixel it projects to);
  * ``other``: the rest.

Sparse points imitate SfM: surface points seen by at least two training views, sampled with a
density falling with distance, weight ``1 / (1 + (t / 3)^2)`` for a hit at distance t, far
content (beyond ``far_radius``) a fixed low weight of 0.03 (a few percent of the points), and
with depth noise along the ray (0.2% near, 10% far, as triangulation with little parallax is).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..parsed import REGION_LABELS
from .raycast import Dome, Lighting, Primitive, apply_matrix, pixel_rays, shade, trace

DEPTH_TOLERANCE = 0.02
"""Relative depth difference under which a point counts as seen by a view."""


@dataclass(frozen=True)
class RenderSettings:
    width: int
    height: int
    supersample: int = 3
    """Sub-samples per pixel side (odd, so the middle one lies on the pixel centre)."""
    far_radius: float = 15.0
    occluded_fraction: float = 0.25
    n_points: int = 3000
    near_noise: float = 0.002
    far_noise: float = 0.1
    far_point_weight: float = 0.03


@dataclass
class ViewRender:
    """image [H, W, 3] in [0, 1]; depth [H, W] camera-space z; points [H, W, 3] centre hits;
    dist [H, W] distance from the scene origin of the hit; sky [H, W] bool."""

    image: np.ndarray
    depth: np.ndarray
    points: np.ndarray
    ray_t: np.ndarray
    origin_dist: np.ndarray
    sky: np.ndarray


def render_view(
    prims: list[Primitive], K: np.ndarray, c2w: np.ndarray, settings: RenderSettings
) -> ViewRender:
    """Ray-cast one view with ``supersample``^2 rays per pixel (box-filtered)."""
    s = settings.supersample
    if s < 1 or s % 2 == 0:
        raise ValueError(f"supersample must be odd and >= 1, got {s}")
    w, h = settings.width, settings.height
    origin, dirs, z_per_t = pixel_rays(K, c2w, w, h, s)
    hits = trace(origin, dirs, prims)
    colors = shade(origin, dirs, hits, prims, Lighting())
    image = colors.reshape(h, w, s * s, 3).mean(axis=2)
    centre = (s * s) // 2  # the middle sub-sample sits on the pixel centre
    t = hits.t.reshape(h, w, s * s)[:, :, centre]
    d = dirs.reshape(h, w, s * s, 3)[:, :, centre]
    z = z_per_t.reshape(h, w, s * s)[:, :, centre]
    prim = hits.prim.reshape(h, w, s * s)[:, :, centre]
    points = origin + t[..., None] * d
    sky_ids = [i for i, p in enumerate(prims) if isinstance(p, Dome)]
    return ViewRender(
        image=image,
        depth=t * z,
        points=points,
        ray_t=t,
        origin_dist=np.linalg.norm(points, axis=-1),
        sky=np.isin(prim, sky_ids),
    )


def count_visible(
    points: np.ndarray, Ks: np.ndarray, w2cs: np.ndarray, depths: np.ndarray
) -> np.ndarray:
    """How many views see each point. points: [M, 3]; Ks: [V, 3, 3]; w2cs: [V, 4, 4];
    depths: [V, H, W] z-depth maps -> counts [M]."""
    counts = np.zeros(len(points), dtype=np.int64)
    height, width = depths.shape[1:]
    for K, w2c, depth in zip(Ks, w2cs, depths):
        cam = apply_matrix(w2c[:3, :3], points) + w2c[:3, 3]
        z = cam[:, 2]
        safe_z = np.where(z > 1e-9, z, 1.0)
        u = K[0, 0] * cam[:, 0] / safe_z + K[0, 2]
        v = K[1, 1] * cam[:, 1] / safe_z + K[1, 2]
        inside = (z > 1e-9) & (u >= 0) & (u < width) & (v >= 0) & (v < height)
        ui = np.clip(u.astype(np.int64), 0, width - 1)
        vi = np.clip(v.astype(np.int64), 0, height - 1)
        seen = inside & (np.abs(depth[vi, ui] - z) <= DEPTH_TOLERANCE * z)
        counts += seen
    return counts


def region_labels(
    view: ViewRender, seen_fraction: np.ndarray, settings: RenderSettings
) -> np.ndarray:
    """uint8 [H, W] labels (see ``REGION_LABELS``). seen_fraction: [H, W] in [0, 1]."""
    labels = np.full(view.depth.shape, REGION_LABELS["other"], dtype=np.uint8)
    far = view.sky | (view.origin_dist > settings.far_radius)
    labels[(~far) & (seen_fraction < settings.occluded_fraction)] = REGION_LABELS["occluded"]
    labels[far] = REGION_LABELS["far"]
    return labels


def sparse_points(
    views: list[ViewRender],
    c2ws: np.ndarray,
    train_ids: list[int],
    seen_counts: list[np.ndarray],
    settings: RenderSettings,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray]:
    """SfM-like points [P, 3] and colours [P, 3] from the training views' centre hits.

    seen_counts[i]: [H, W] number of training views that see the centre hit of view i.
    """
    cand_pts, cand_rgb, cand_w, cand_far, cand_eye = [], [], [], [], []
    for i in train_ids:
        view = views[i]
        ok = (~view.sky) & (seen_counts[i] >= 2)
        far = view.origin_dist[ok] > settings.far_radius
        weight = 1.0 / (1.0 + (view.ray_t[ok] / 3.0) ** 2)
        weight = np.where(far, settings.far_point_weight, weight)
        cand_pts.append(view.points[ok])
        cand_rgb.append(view.image[ok])
        cand_w.append(weight)
        cand_far.append(far)
        cand_eye.append(np.broadcast_to(c2ws[i][:3, 3], (int(ok.sum()), 3)))
    pts = np.concatenate(cand_pts)
    rgb = np.concatenate(cand_rgb)
    weights = np.concatenate(cand_w)
    far = np.concatenate(cand_far)
    eyes = np.concatenate(cand_eye)
    n = min(settings.n_points, len(pts))
    # Weighted sampling without replacement (Efraimidis-Spirakis): keep the n largest u^(1/w).
    keys = np.log(rng.random(len(pts))) / np.maximum(weights, 1e-12)
    keep = np.argsort(-keys)[:n]
    pts, rgb, far, eyes = pts[keep], rgb[keep], far[keep], eyes[keep]
    sigma = np.where(far, settings.far_noise, settings.near_noise)
    pts = eyes + (pts - eyes) * (1.0 + sigma * rng.standard_normal(n))[:, None]
    return pts, rgb
