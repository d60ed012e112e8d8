"""Procedural textures for the built-in scenes: pure functions of 3D surface points.

Solid (3D) textures need no UV maps, so the same pattern works on planes, boxes, spheres
and cylinders. Every pattern is deterministic: randomness comes from an integer hash of the
lattice cell and a ``seed``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

_MASK = np.uint64(0xFFFFFFFF)


def hash01(cells: np.ndarray, seed: int) -> np.ndarray:
    """A value in [0, 1) per integer cell. cells: [M, D] ints -> [M]."""
    h = np.full(len(cells), np.uint64((seed * 2654435761 + 97531) & 0xFFFFFFFF), dtype=np.uint64)
    primes = (np.uint64(73856093), np.uint64(19349663), np.uint64(83492791), np.uint64(2246822519))
    with np.errstate(over="ignore"):
        for axis in range(cells.shape[1]):
            h ^= (cells[:, axis].astype(np.int64).astype(np.uint64) * primes[axis % 4]) & _MASK
            # xorshift-multiply mixing so neighbouring cells decorrelate.
            h ^= h >> np.uint64(15)
            h = (h * np.uint64(0x2C1B3C6D)) & _MASK
            h ^= h >> np.uint64(12)
            h = (h * np.uint64(0x297A2D39)) & _MASK
            h ^= h >> np.uint64(15)
    return (h & np.uint64(0xFFFFFF)).astype(np.float64) / float(0x1000000)


def value_noise(points: np.ndarray, frequency: float, seed: int) -> np.ndarray:
    """Smooth noise in [0, 1]: hashed lattice values, trilinear with a smoothstep. points: [M, D]."""
    p = points * frequency
    base = np.floor(p)
    frac = p - base
    w = frac * frac * (3.0 - 2.0 * frac)
    dims = p.shape[1]
    out = np.zeros(len(p))
    for corner in range(2**dims):
        offs = np.array([(corner >> k) & 1 for k in range(dims)], dtype=np.float64)
        weight = np.prod(np.where(offs > 0, w, 1.0 - w), axis=1)
        out += weight * hash01((base + offs).astype(np.int64), seed)
    return out


def fbm(points: np.ndarray, frequency: float, seed: int, octaves: int = 4) -> np.ndarray:
    """Fractal sum of value noise in [0, 1]: detail at every scale (rock, clouds)."""
    total, amp, norm = np.zeros(len(points)), 1.0, 0.0
    for octave in range(octaves):
        total += amp * value_noise(points, frequency * 2**octave, seed + 17 * octave)
        norm += amp
        amp *= 0.5
    return total / norm


def ring_arc(points: np.ndarray) -> np.ndarray:
    """Distance along a ring around the z axis, [M]. The angle is measured so that its jump
    (from -pi to pi) lies towards -y, a direction no built-in camera looks at."""
    angle = np.arctan2(-points[:, 0], points[:, 1])
    return angle * np.linalg.norm(points[:, :2], axis=1)


def palette_pick(palette: np.ndarray, u: np.ndarray) -> np.ndarray:
    """palette: [C, 3]; u: [M] in [0, 1) -> colours [M, 3]."""
    idx = np.clip((u * len(palette)).astype(np.int64), 0, len(palette) - 1)
    return palette[idx]


@dataclass
class Tiles:
    """Ground tiles: each tile a palette colour, dark grout, speckle; fades far away to the
    mean colour (``fade_start``..``fade_end`` from the origin) as real ground loses detail."""

    size: float
    palette: np.ndarray
    seed: int
    grout: float = 0.06
    fade_start: float = 12.0
    fade_end: float = 30.0

    def __call__(self, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
        xy = points[:, :2] / self.size
        cells = np.floor(xy).astype(np.int64)
        frac = xy - cells
        color = palette_pick(self.palette, hash01(cells, self.seed))
        speckle = 0.75 + 0.5 * value_noise(points[:, :2], 4.0 / self.size, self.seed + 1)
        color = color * speckle[:, None]
        in_grout = (frac.min(axis=1) < self.grout) | (frac.max(axis=1) > 1.0 - self.grout)
        color[in_grout] = color[in_grout] * 0.3
        dist = np.linalg.norm(points[:, :2], axis=1)
        fade = np.clip((dist - self.fade_start) / max(self.fade_end - self.fade_start, 1e-9), 0, 1)
        mean = self.palette.mean(axis=0) * 0.9
        return np.clip(color * (1 - fade[:, None]) + mean * fade[:, None], 0, 1)


@dataclass
class Checker:
    """3D checker of two colours with a hashed tint per cell."""

    size: float
    color_a: np.ndarray
    color_b: np.ndarray
    seed: int
    tint: float = 0.25

    def __call__(self, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
        # Nudge inward along the normal so faces lying on a cell boundary pick one cell.
        cells = np.floor((points - 1e-4 * normals) / self.size).astype(np.int64)
        parity = (cells.sum(axis=1) % 2 == 0)[:, None]
        color = np.where(parity, self.color_a, self.color_b)
        tint = 1.0 - self.tint + 2 * self.tint * hash01(cells, self.seed)
        return np.clip(color * tint[:, None], 0, 1)


@dataclass
class Stripes:
    """Sharp stripes along ``direction`` with ``period``, cycling through ``palette``."""

    direction: np.ndarray
    period: float
    palette: np.ndarray

    def __call__(self, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
        d = self.direction
        coord = (points[:, 0] * d[0] + points[:, 1] * d[1] + points[:, 2] * d[2]) / self.period
        idx = np.floor(coord).astype(np.int64) % len(self.palette)
        return self.palette[idx]


@dataclass
class Mosaic:
    """Fine detail: small hashed-colour cells overlaid with thin diagonal lines.

    The high-frequency pattern used where a trap needs detail (e.g. inside the cabinet)."""

    size: float
    palette: np.ndarray
    seed: int

    def __call__(self, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
        cells = np.floor((points - 1e-4 * normals) / self.size).astype(np.int64)
        color = palette_pick(self.palette, hash01(cells, self.seed))
        diag = (points[:, 0] + points[:, 1] + points[:, 2]) / (2.5 * self.size)
        lines = np.abs(diag - np.round(diag)) < 0.12
        color = np.where(lines[:, None], 1.0 - color, color)
        return np.clip(color, 0, 1)


@dataclass
class Facades:
    """Skyline facades on a ring: one colour per building (azimuth bin), a window grid."""

    n_buildings: int
    window_width: float
    window_height: float
    seed: int

    def __call__(self, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
        azimuth = np.arctan2(points[:, 1], points[:, 0])
        building = np.floor((azimuth + np.pi) / (2 * np.pi) * self.n_buildings).astype(np.int64)
        base = 0.35 + 0.35 * hash01(building[:, None], self.seed)
        hue = hash01(building[:, None], self.seed + 1)
        facade = np.stack([base, base * (0.85 + 0.2 * hue), base * (0.75 + 0.3 * (1 - hue))], 1)
        arc = ring_arc(points)
        col = np.floor(arc / self.window_width).astype(np.int64)
        row = np.floor(points[:, 2] / self.window_height).astype(np.int64)
        fx = arc / self.window_width - col
        fy = points[:, 2] / self.window_height - row
        is_window = (fx > 0.3) & (fx < 0.8) & (fy > 0.25) & (fy < 0.8)
        lit = hash01(np.stack([col, row], 1), self.seed + 2) > 0.55
        window = np.where(lit[:, None], np.array([0.95, 0.85, 0.45]), np.array([0.1, 0.12, 0.18]))
        return np.where(is_window[:, None], window, facade)


@dataclass
class Rock:
    """Ridge rock on a ring around the z axis: fractal noise with strata, grey-brown."""

    frequency: float
    seed: int

    def __call__(self, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
        # 2D noise over (distance along the ring, height): half the lattice corners of 3D noise.
        arc = ring_arc(points)
        n = fbm(np.stack([arc, points[:, 2]], axis=1), self.frequency, self.seed, octaves=5)
        strata = 0.5 + 0.5 * np.sin(points[:, 2] * self.frequency * 6.0 + 4.0 * n)
        shade = 0.25 + 0.45 * n + 0.2 * strata
        return np.clip(np.stack([shade * 0.95, shade * 0.85, shade * 0.75], 1), 0, 1)


@dataclass
class Sky:
    """Blue gradient by elevation with soft clouds (low frequency: easy for any method)."""

    seed: int

    def __call__(self, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
        unit = points / np.maximum(np.linalg.norm(points, axis=1, keepdims=True), 1e-12)
        elevation = np.clip(unit[:, 2], 0.0, 1.0)
        horizon = np.array([0.78, 0.85, 0.95])
        zenith = np.array([0.3, 0.5, 0.85])
        color = horizon + (zenith - horizon) * np.sqrt(elevation)[:, None]
        cloud = np.clip((fbm(unit, 3.0, self.seed, octaves=3) - 0.55) * 3.0, 0, 1)
        return np.clip(color * (1 - cloud[:, None]) + 0.95 * cloud[:, None], 0, 1)
