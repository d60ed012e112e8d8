"""A smooth camera path through key cameras (for fly-through videos of a scene).

Positions follow a centripetal Catmull-Rom spline through the key camera centres (it passes
through every key and, unlike the uniform variant, never forms cusps or loops inside a segment);
orientations are slerped between consecutive key rotations, so every frame's rotation is exactly
orthonormal. Intrinsics are interpolated linearly after bringing every key to the first key's
image size. All maths in float64; the cameras come out float32.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal, Sequence

import numpy as np
import torch

from exploregs_plugin.cameras import Camera

CameraOrder = Literal["nearest", "name", "given"]
Trajectory = Literal["test", "train", "path", "path-all"]
SPLINE_ALPHA = 0.5
"""Knot exponent of the Catmull-Rom spline: 0 uniform, 0.5 centripetal, 1 chordal."""
_COINCIDENT = 1e-12
"""Key centres closer than this (relative to the path size) count as the same point."""
GROUP_GAP = 4.0
"""Cameras farther apart than this x the median nearest-neighbour spacing belong to different
groups: a path between groups would cross space that no training camera saw."""


# ----------------------------------------------------------------------------- rotations
def rotation_to_quat(rot: np.ndarray) -> np.ndarray:
    """Rotation matrix [3, 3] -> unit quaternion [4] (w, x, y, z) with w >= 0.

    Shepperd's method: take the square root of the largest of 1 + trace and 1 + 2 R_ii - trace,
    so the divisor is never small.
    """
    m = np.asarray(rot, dtype=np.float64)
    trace = m[0, 0] + m[1, 1] + m[2, 2]
    candidates = [trace, m[0, 0], m[1, 1], m[2, 2]]
    i = int(np.argmax(candidates))
    if i == 0:
        s = 2.0 * math.sqrt(max(1.0 + trace, 1e-300))
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    elif i == 1:
        s = 2.0 * math.sqrt(max(1.0 + m[0, 0] - m[1, 1] - m[2, 2], 1e-300))
        q = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
    elif i == 2:
        s = 2.0 * math.sqrt(max(1.0 + m[1, 1] - m[0, 0] - m[2, 2], 1e-300))
        q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
    else:
        s = 2.0 * math.sqrt(max(1.0 + m[2, 2] - m[0, 0] - m[1, 1], 1e-300))
        q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
    quat = np.array(q)
    quat /= max(np.linalg.norm(quat), 1e-300)
    return quat if quat[0] >= 0.0 else -quat


def quat_to_rotation(quat: np.ndarray) -> np.ndarray:
    """Quaternion [4] (w, x, y, z), any non-zero length -> rotation matrix [3, 3]."""
    norm = float(np.linalg.norm(quat))
    if norm < 1e-300:
        raise ValueError("cannot turn a zero quaternion into a rotation")
    w, x, y, z = np.asarray(quat, dtype=np.float64) / norm
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def slerp(q0: np.ndarray, q1: np.ndarray, t: float) -> np.ndarray:
    """Unit-quaternion spherical interpolation along the shorter arc; t in [0, 1].

    q(t) = sin((1-t) theta) / sin(theta) q0 + sin(t theta) / sin(theta) q1, cos(theta) = q0.q1;
    for nearly equal quaternions (sin(theta) ~ 0) the normalised linear blend is used.
    """
    q0 = np.asarray(q0, dtype=np.float64) / np.linalg.norm(q0)
    q1 = np.asarray(q1, dtype=np.float64) / np.linalg.norm(q1)
    dot = float(np.dot(q0, q1))
    if dot < 0.0:  # q and -q are the same rotation: take the short way round
        q1, dot = -q1, -dot
    if dot > 1.0 - 1e-10:
        q = (1.0 - t) * q0 + t * q1
    else:
        theta = math.acos(min(dot, 1.0))
        sin_theta = math.sin(theta)
        q = (math.sin((1.0 - t) * theta) * q0 + math.sin(t * theta) * q1) / sin_theta
    return q / np.linalg.norm(q)


def rotation_angle(q0: np.ndarray, q1: np.ndarray) -> float:
    """Angle in radians of the rotation between unit quaternions q0 and q1 (0 to pi)."""
    return 2.0 * math.acos(min(abs(float(np.dot(q0, q1))), 1.0))


# ----------------------------------------------------------------------------- positions
def _knot(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.linalg.norm(b - a)) ** SPLINE_ALPHA


def catmull_rom_segment(p0: np.ndarray, p1: np.ndarray, p2: np.ndarray, p3: np.ndarray, u: float) -> np.ndarray:
    """Point at fraction ``u`` in [0, 1] of the centripetal Catmull-Rom segment p1 -> p2 (each [3]).

    Barry-Goldman pyramid with knots t_{i+1} = t_i + |p_{i+1} - p_i|^alpha. Neighbours that
    coincide with p1 or p2 are replaced by reflections (2 p1 - p2, 2 p2 - p1), so no knot
    interval is zero; a zero-length segment stays at p1.
    """
    span = float(np.linalg.norm(p2 - p1))
    if span <= _COINCIDENT:
        return p1.copy()
    if float(np.linalg.norm(p1 - p0)) <= _COINCIDENT * max(span, 1.0):
        p0 = 2.0 * p1 - p2
    if float(np.linalg.norm(p3 - p2)) <= _COINCIDENT * max(span, 1.0):
        p3 = 2.0 * p2 - p1
    t0 = 0.0
    t1 = t0 + _knot(p0, p1)
    t2 = t1 + _knot(p1, p2)
    t3 = t2 + _knot(p2, p3)
    t = t1 + u * (t2 - t1)
    a1 = ((t1 - t) * p0 + (t - t0) * p1) / (t1 - t0)
    a2 = ((t2 - t) * p1 + (t - t1) * p2) / (t2 - t1)
    a3 = ((t3 - t) * p2 + (t - t2) * p3) / (t3 - t2)
    b1 = ((t2 - t) * a1 + (t - t0) * a2) / (t2 - t0)
    b2 = ((t3 - t) * a2 + (t - t1) * a3) / (t3 - t1)
    return ((t2 - t) * b1 + (t - t1) * b2) / (t2 - t1)


# ----------------------------------------------------------------------------- key choice
def order_cameras(cameras: Sequence[Camera], order: CameraOrder = "nearest") -> list[int]:
    """Indices of ``cameras`` in path order.

    nearest: start at the camera farthest from the mean centre (an end of an arc or a line)
    and repeatedly go to the nearest camera not yet visited; name: sorted by name (capture
    order for most datasets); given: as listed.
    """
    n = len(cameras)
    if order == "given":
        return list(range(n))
    if order == "name":
        return sorted(range(n), key=lambda i: (cameras[i].name, i))
    if order != "nearest":
        raise ValueError(f"unknown camera order {order!r}; choose nearest, name or given")
    if n == 0:
        return []
    centers = np.stack([c.camera_center.detach().double().numpy() for c in cameras])
    current = int(np.argmax(np.linalg.norm(centers - centers.mean(axis=0), axis=1)))
    path, left = [current], set(range(n)) - {current}
    while left:
        rest = sorted(left)
        dist = np.linalg.norm(centers[rest] - centers[current], axis=1)
        current = rest[int(np.argmin(dist))]
        path.append(current)
        left.remove(current)
    return path


def camera_groups(cameras: Sequence[Camera], gap: float = GROUP_GAP) -> list[list[int]]:
    """Indices of ``cameras`` split into groups, largest first: the connected components of the
    graph that links two cameras closer than ``gap`` x the median distance of a camera to its
    nearest neighbour (single linkage)."""
    n = len(cameras)
    if n <= 2:
        return [list(range(n))] if n else []
    centers = np.stack([c.camera_center.detach().double().cpu().numpy() for c in cameras])
    dist = np.linalg.norm(centers[:, None] - centers[None], axis=-1)
    np.fill_diagonal(dist, np.inf)
    link = dist <= gap * max(float(np.median(dist.min(axis=1))), 1e-12)
    groups, seen = [], set()
    for start in range(n):
        if start in seen:
            continue
        stack, group = [start], []
        seen.add(start)
        while stack:
            i = stack.pop()
            group.append(i)
            for j in np.flatnonzero(link[i]):
                if int(j) not in seen:
                    seen.add(int(j))
                    stack.append(int(j))
        groups.append(sorted(group))
    return sorted(groups, key=lambda g: (-len(g), g[0]))


def subsample_keys(indices: Sequence[int], max_keys: int | None) -> list[int]:
    """At most ``max_keys`` evenly spread entries of ``indices``, first and last kept."""
    indices = list(indices)
    if max_keys is None or len(indices) <= max_keys:
        return indices
    if max_keys < 2:
        raise ValueError(f"max_keys must be >= 2, got {max_keys}")
    picks = np.round(np.linspace(0, len(indices) - 1, max_keys)).astype(int)
    return [indices[i] for i in picks]


# ----------------------------------------------------------------------------- the path
@dataclass
class CameraPath:
    """Interpolated cameras plus where the keys fell: ``cameras[key_frames[i]]`` is key i."""

    cameras: list[Camera]
    key_frames: list[int]


def _frames_per_segment(centers: np.ndarray, quats: np.ndarray, num_frames: int, loop: bool) -> list[int]:
    """Split ``num_frames`` over the segments in proportion to how far each moves and turns."""
    n = len(centers)
    pairs = [(i, (i + 1) % n) for i in range(n if loop else n - 1)]
    dist = np.array([np.linalg.norm(centers[b] - centers[a]) for a, b in pairs])
    angle = np.array([rotation_angle(quats[a], quats[b]) for a, b in pairs])
    weight = np.zeros(len(pairs))
    for part in (dist, angle):
        if part.sum() > 0.0:
            weight += part / part.sum()
    if weight.sum() <= 0.0:  # all keys identical: spread evenly
        weight[:] = 1.0
    frames = num_frames - (0 if loop else 1)  # an open path ends on its last key
    return [max(1, int(round(frames * w / weight.sum()))) for w in weight]


def interpolate_path(
    keys: Sequence[Camera], num_frames: int, loop: bool = False, width: int | None = None, height: int | None = None
) -> CameraPath:
    """A smooth path through ``keys`` (in the given order), about ``num_frames`` frames.

    Frames are shared out between segments in proportion to their length and turn, at least
    one each, so the exact count can differ a little from ``num_frames``. The image size is
    ``width`` x ``height`` (default: the first key's); intrinsics of every key are rescaled to it.
    """
    if len(keys) < 2:
        raise ValueError(f"a camera path needs at least 2 key cameras, got {len(keys)}")
    if num_frames < len(keys):
        raise ValueError(f"num_frames ({num_frames}) must be at least the number of key cameras ({len(keys)})")
    out_w = width or keys[0].width
    out_h = height or keys[0].height
    view = [k.viewmat.detach().double().numpy() for k in keys]
    rot_c2w = [v[:3, :3].T for v in view]
    centers = np.stack([-r @ v[:3, 3] for r, v in zip(rot_c2w, view)])
    quats = np.stack([rotation_to_quat(r) for r in rot_c2w])
    intr = np.stack([_intrinsics(k, out_w, out_h) for k in keys])  # [n, 4] fx fy cx cy
    counts = _frames_per_segment(centers, quats, num_frames, loop)
    n = len(keys)

    def point(i: int) -> np.ndarray:  # neighbour lookup: wrap on a loop, extrapolate at open ends
        if loop:
            return centers[i % n]
        if 0 <= i < n:
            return centers[i]
        a, b, c = (centers[0], centers[1], centers[min(2, n - 1)]) if i < 0 else \
            (centers[n - 1], centers[n - 2], centers[max(n - 3, 0)])
        # ghost point one step beyond the end: quadratic extrapolation 3a - 3b + c keeps the
        # end segment's curvature like its neighbour's (linear 2a - b with only two keys)
        return 3.0 * a - 3.0 * b + c if n >= 3 else 2.0 * a - b

    cameras: list[Camera] = []
    key_frames: list[int] = []
    for seg, count in enumerate(counts):
        a, b = seg, (seg + 1) % n
        key_frames.append(len(cameras))
        for j in range(count):
            u = j / count
            center = catmull_rom_segment(point(seg - 1), point(seg), point(seg + 1), point(seg + 2), u)
            rot = quat_to_rotation(slerp(quats[a], quats[b], u))
            cameras.append(_camera(rot, center, (1.0 - u) * intr[a] + u * intr[b], out_w, out_h, len(cameras)))
    if not loop:
        key_frames.append(len(cameras))
        cameras.append(_camera(quat_to_rotation(quats[-1]), centers[-1], intr[-1], out_w, out_h, len(cameras)))
    return CameraPath(cameras, key_frames)


def _intrinsics(camera: Camera, width: int, height: int) -> np.ndarray:
    """[4] fx fy cx cy of ``camera`` rescaled to an image of ``width`` x ``height``."""
    k = camera.K.detach().double().numpy()
    sx, sy = width / camera.width, height / camera.height
    return np.array([k[0, 0] * sx, k[1, 1] * sy, k[0, 2] * sx, k[1, 2] * sy])


def _camera(rot_c2w: np.ndarray, center: np.ndarray, intr: np.ndarray, width: int, height: int, index: int) -> Camera:
    """World-to-camera [R^T | -R^T C] from a camera-to-world rotation R and centre C."""
    viewmat = np.eye(4)
    viewmat[:3, :3] = rot_c2w.T
    viewmat[:3, 3] = -rot_c2w.T @ center
    K = np.array([[intr[0], 0.0, intr[2]], [0.0, intr[1], intr[3]], [0.0, 0.0, 1.0]])
    return Camera(torch.from_numpy(viewmat).float(), torch.from_numpy(K).float(), width, height, f"path_{index:04d}")



def trajectory_cameras(
    train: Sequence[Camera],
    test: Sequence[Camera],
    trajectory: Trajectory,
    num_frames: int = 120,
    max_keys: int | None = 16,
    order: CameraOrder = "nearest",
    loop: bool = False,
) -> list[Camera]:
    """The cameras to render: the test or training views as they are, or a smooth path through
    up to ``max_keys`` training cameras taken in ``order``: ``path`` through the largest group of
    training cameras (:func:`camera_groups`), so it stays where the cameras saw the scene;
    ``path-all`` through all of them, across the gaps between groups."""
    if trajectory == "test":
        if not test:
            raise ValueError("the dataset has no test cameras; use --trajectory train or path")
        return list(test)
    if trajectory == "train":
        return list(train)
    if trajectory not in ("path", "path-all"):
        raise ValueError(f"unknown trajectory {trajectory!r}; choose test, train, path or path-all")
    # with two or more cameras the largest group has two or more: some camera's nearest
    # neighbour lies within the median spacing
    members = list(range(len(train))) if trajectory == "path-all" or not train else camera_groups(train)[0]
    group = [train[i] for i in members]
    keys = subsample_keys(order_cameras(group, order), max_keys)
    return interpolate_path([group[i] for i in keys], num_frames, loop=loop).cameras
