"""A small numpy ray caster for the built-in scenes (analytic shapes, nearest hit, shading).

Independent of the Gaussian rasterizer on purpose: the scenes are ground truth for it.
World frame: z up. Rays: ``origin [3]`` shared, ``dirs [M, 3]`` unit length. Every
``intersect`` returns ``t [M]`` (distance along the ray, ``inf`` for a miss) and outward
``normals [M, 3]``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

T_MIN = 1e-6
"""Hits closer than this along a ray are ignored (self-intersection guard)."""

Texture = Callable[[np.ndarray, np.ndarray], np.ndarray]
"""(points [M, 3], normals [M, 3]) -> albedo [M, 3] in [0, 1]."""


@dataclass
class Material:
    """How a surface looks: an albedo texture, lit (diffuse + mild specular) or emissive."""

    texture: Texture
    lit: bool = True
    specular: float = 0.12
    """Weight of the Phong highlight: the mild view-dependent term."""


def dot3(vecs: np.ndarray, v: np.ndarray) -> np.ndarray:
    """vecs [M, 3] . v [3] -> [M], written out: for 3-vectors this beats a BLAS call, which
    also spawns threads that fight for the cores."""
    return vecs[:, 0] * v[0] + vecs[:, 1] * v[1] + vecs[:, 2] * v[2]


def apply_matrix(mat: np.ndarray, vecs: np.ndarray) -> np.ndarray:
    """mat [3, 3] applied to each row of vecs [M, 3] -> [M, 3] (= vecs @ mat.T), written out."""
    return vecs[:, 0:1] * mat[:, 0] + vecs[:, 1:2] * mat[:, 1] + vecs[:, 2:3] * mat[:, 2]


def _safe_div(num: np.ndarray, den: np.ndarray) -> np.ndarray:
    """num / den with den near 0 replaced by a tiny signed value (rays parallel to a face)."""
    den = np.where(np.abs(den) < 1e-12, np.where(den < 0, -1e-12, 1e-12), den)
    return num / den


@dataclass
class GroundPlane:
    """The infinite plane z = height, facing +z."""

    height: float
    material: Material

    def intersect(self, origin: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        t = _safe_div(np.full(len(dirs), self.height - origin[2]), dirs[:, 2])
        t = np.where(t > T_MIN, t, np.inf)
        normals = np.zeros_like(dirs)
        normals[:, 2] = 1.0
        return t, normals


@dataclass
class Box:
    """Axis-aligned box [lo, hi] (slab method)."""

    lo: np.ndarray
    hi: np.ndarray
    material: Material

    def bounds(self) -> tuple[np.ndarray, float]:
        return (self.lo + self.hi) / 2, float(np.linalg.norm(self.hi - self.lo)) / 2

    def intersect(self, origin: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        inv = _safe_div(np.ones_like(dirs), dirs)
        t0 = (self.lo - origin) * inv
        t1 = (self.hi - origin) * inv
        tmin = np.minimum(t0, t1)
        tmax = np.maximum(t0, t1)
        t_near = tmin.max(axis=1)
        t_far = tmax.min(axis=1)
        axis = tmin.argmax(axis=1)
        # Entering hit when the origin is outside; the exit hit when inside (not used here).
        t = np.where(t_near > T_MIN, t_near, t_far)
        hit = (t_near <= t_far) & (t > T_MIN)
        t = np.where(hit, t, np.inf)
        normals = np.zeros_like(dirs)
        rows = np.arange(len(dirs))
        normals[rows, axis] = -np.sign(dirs[rows, axis])
        return t, normals


@dataclass
class Sphere:
    center: np.ndarray
    radius: float
    material: Material

    def bounds(self) -> tuple[np.ndarray, float]:
        return self.center, self.radius

    def intersect(self, origin: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        oc = origin - self.center
        b = dot3(dirs, oc)
        c = oc @ oc - self.radius**2
        disc = b * b - c
        root = np.sqrt(np.maximum(disc, 0.0))
        t = np.where(-b - root > T_MIN, -b - root, -b + root)
        t = np.where((disc >= 0) & (t > T_MIN), t, np.inf)
        points = origin + np.where(np.isfinite(t), t, 0.0)[:, None] * dirs
        normals = (points - self.center) / self.radius
        return t, normals


@dataclass
class Cylinder:
    """Vertical capped cylinder: axis through ``center_xy``, from z0 to z1."""

    center_xy: np.ndarray
    radius: float
    z0: float
    z1: float
    material: Material

    def bounds(self) -> tuple[np.ndarray, float]:
        half = (self.z1 - self.z0) / 2
        center = np.array([self.center_xy[0], self.center_xy[1], self.z0 + half])
        return center, float(np.hypot(self.radius, half))

    def intersect(self, origin: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        ox, oy = origin[0] - self.center_xy[0], origin[1] - self.center_xy[1]
        dx, dy = dirs[:, 0], dirs[:, 1]
        a = dx * dx + dy * dy
        b = 2 * (ox * dx + oy * dy)
        c = ox * ox + oy * oy - self.radius**2
        disc = b * b - 4 * a * c
        root = np.sqrt(np.maximum(disc, 0.0))
        t_side = _safe_div(-b - root, 2 * a)
        z = origin[2] + t_side * dirs[:, 2]
        side_ok = (disc >= 0) & (a > 1e-12) & (t_side > T_MIN) & (z >= self.z0) & (z <= self.z1)
        t_side = np.where(side_ok, t_side, np.inf)
        best_t = t_side
        normals = np.zeros_like(dirs)
        px = ox + np.where(side_ok, t_side, 0.0) * dx
        py = oy + np.where(side_ok, t_side, 0.0) * dy
        normals[:, 0], normals[:, 1] = px / self.radius, py / self.radius
        for cap_z, sign in ((self.z1, 1.0), (self.z0, -1.0)):
            t_cap = _safe_div(np.full(len(dirs), cap_z - origin[2]), dirs[:, 2])
            qx, qy = ox + t_cap * dx, oy + t_cap * dy
            cap_ok = (t_cap > T_MIN) & (qx * qx + qy * qy <= self.radius**2) & (t_cap < best_t)
            best_t = np.where(cap_ok, t_cap, best_t)
            normals[cap_ok] = np.array([0.0, 0.0, sign])
        return best_t, normals


@dataclass
class HorizonRing:
    """The inside of a vertical cylinder of ``radius`` around the z axis, from z = 0 up to a
    height profile ``height_fn(azimuth [M]) -> [M]``: a skyline or a ridge seen from within."""

    radius: float
    height_fn: Callable[[np.ndarray], np.ndarray]
    material: Material
    max_height: float = np.inf
    """An upper bound of ``height_fn``: rays above it skip the (costly) profile evaluation."""

    def intersect(self, origin: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        ox, oy = origin[0], origin[1]
        dx, dy = dirs[:, 0], dirs[:, 1]
        a = dx * dx + dy * dy
        b = 2 * (ox * dx + oy * dy)
        c = ox * ox + oy * oy - self.radius**2  # < 0: the origin is inside the ring
        disc = np.maximum(b * b - 4 * a * c, 0.0)
        t = _safe_div(-b + np.sqrt(disc), 2 * a)
        px, py = ox + t * dx, oy + t * dy
        z = origin[2] + t * dirs[:, 2]
        ok = (a > 1e-12) & (t > T_MIN) & (z >= 0.0) & (z <= self.max_height)
        ok[ok] = z[ok] <= self.height_fn(np.arctan2(py[ok], px[ok]))
        t = np.where(ok, t, np.inf)
        normals = np.stack([-px, -py, np.zeros_like(px)], axis=1) / self.radius
        return t, normals


@dataclass
class Dome:
    """The inside of a sphere of ``radius`` around the origin: the sky. Every ray hits it."""

    radius: float
    material: Material

    def intersect(self, origin: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        b = dot3(dirs, origin)
        c = origin @ origin - self.radius**2
        t = -b + np.sqrt(np.maximum(b * b - c, 0.0))
        points = origin + t[:, None] * dirs
        return t, -points / self.radius


Primitive = GroundPlane | Box | Sphere | Cylinder | HorizonRing | Dome


@dataclass
class Hits:
    """Nearest hits of M rays: t [M] (inf = miss), normals [M, 3], prim [M] (-1 = miss)."""

    t: np.ndarray
    normals: np.ndarray
    prim: np.ndarray


def trace(origin: np.ndarray, dirs: np.ndarray, prims: list[Primitive]) -> Hits:
    """Nearest hit of each ray among ``prims``. origin: [3]; dirs: [M, 3] unit."""
    best_t = np.full(len(dirs), np.inf)
    best_n = np.zeros_like(dirs)
    best_p = np.full(len(dirs), -1, dtype=np.int64)
    for index, prim in enumerate(prims):
        rows = _candidates(prim, origin, dirs, best_t)
        t, normals = prim.intersect(origin, dirs if rows is None else dirs[rows])
        if rows is None:
            rows = np.arange(len(dirs))
        closer = t < best_t[rows]
        best_t[rows[closer]] = t[closer]
        best_n[rows[closer]] = normals[closer]
        best_p[rows[closer]] = index
    return Hits(best_t, best_n, best_p)


def _candidates(prim: Primitive, origin: np.ndarray, dirs: np.ndarray, best_t: np.ndarray) -> np.ndarray | None:
    """Rows of rays that can hit ``prim`` closer than their current best (bounding-sphere test),
    or None for unbounded primitives (every ray is a candidate)."""
    if not hasattr(prim, "bounds"):
        return None
    center, radius = prim.bounds()
    oc = origin - center
    b = dot3(dirs, oc)
    disc = b * b - (oc @ oc - radius * radius)
    root = np.sqrt(np.maximum(disc, 0.0))
    return np.nonzero((disc >= 0) & (-b + root > T_MIN) & (-b - root < best_t))[0]


@dataclass(frozen=True)
class Lighting:
    """A sun and a sky: colour = albedo * (ambient + diffuse * max(n.L, 0)) + highlight."""

    sun_dir: tuple[float, float, float] = (0.45, 0.3, 0.84)
    ambient: float = 0.4
    diffuse: float = 0.65
    shininess: float = 12.0


def shade(
    origin: np.ndarray, dirs: np.ndarray, hits: Hits, prims: list[Primitive], light: Lighting
) -> np.ndarray:
    """RGB [M, 3] in [0, 1] for traced rays (misses are black; scenes close with a Dome)."""
    colors = np.zeros_like(dirs)
    sun = np.asarray(light.sun_dir, dtype=np.float64)
    sun = sun / np.linalg.norm(sun)
    points = origin + np.where(np.isfinite(hits.t), hits.t, 0.0)[:, None] * dirs
    for index, prim in enumerate(prims):
        sel = hits.prim == index
        if not sel.any():
            continue
        mat = prim.material
        normals = hits.normals[sel]
        albedo = mat.texture(points[sel], normals)
        if not mat.lit:
            colors[sel] = albedo
            continue
        # Face the normal towards the viewer so thin slabs are lit from both sides.
        view = dirs[sel]
        facing = np.where((np.sum(normals * view, axis=1) > 0)[:, None], -normals, normals)
        lambert = np.clip(dot3(facing, sun), 0.0, None)
        reflected = view - 2.0 * np.sum(view * facing, axis=1, keepdims=True) * facing
        highlight = mat.specular * np.clip(dot3(reflected, sun), 0.0, None) ** light.shininess
        colors[sel] = albedo * (light.ambient + light.diffuse * lambert)[:, None] + highlight[:, None]
    return np.clip(colors, 0.0, 1.0)


def pixel_rays(
    K: np.ndarray, c2w: np.ndarray, width: int, height: int, supersample: int = 1
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rays through a ``supersample`` x ``supersample`` grid of points in every pixel.

    Pixel (u, v) covers [u, u+1) x [v, v+1); sub-sample (i, j) sits at u + (i + 0.5) / s, so
    an odd ``s`` puts the middle sub-sample on the pixel centre u + 0.5.
    Returns origin [3], unit dirs [H * W * s * s, 3] ordered (row, col, sub_y, sub_x), and
    ``z_per_t`` [same] (camera-space z per unit distance, to turn t into z-depth).
    """
    s = supersample
    offs = (np.arange(s) + 0.5) / s
    v = (np.arange(height)[:, None] + offs[None, :]).reshape(-1)  # [H*s]
    u = (np.arange(width)[:, None] + offs[None, :]).reshape(-1)  # [W*s]
    vv, uu = np.meshgrid(v, u, indexing="ij")  # [H*s, W*s]
    # Reorder to (row, col, sub_y, sub_x) so a reshape to [H, W, s*s] groups each pixel.
    uu = uu.reshape(height, s, width, s).transpose(0, 2, 1, 3).reshape(-1)
    vv = vv.reshape(height, s, width, s).transpose(0, 2, 1, 3).reshape(-1)
    pix = np.stack([uu, vv, np.ones_like(uu)], axis=1)
    cam = apply_matrix(np.linalg.inv(K), pix)  # camera-space directions with z = 1
    norm = np.linalg.norm(cam, axis=1, keepdims=True)
    dirs_cam = cam / norm
    dirs = apply_matrix(c2w[:3, :3], dirs_cam)
    return c2w[:3, 3].copy(), dirs, dirs_cam[:, 2]
