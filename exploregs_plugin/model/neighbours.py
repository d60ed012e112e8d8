"""Mean distance of each point to its nearest neighbours: the initial Gaussians' scales.

Every point against every other costs P^2 distances: 10 s of one thread at 40,000 SfM points, a
minute at 100,000, what a capture of a few hundred photos gives. A uniform grid finds the same
neighbours from a few cells around each point. The result is the brute force's, bit for bit: each
distance is the same `cdist` of the same two rows (its non-matrix-product path computes every pair
on its own), the k + 1 smallest of a row are the same numbers whichever farther points the row
holds, and their mean is taken once over the same [P, k] values.
"""

from __future__ import annotations

import torch
from torch import Tensor

BRUTE_FORCE_BELOW = 8192
"""Clouds this small take every pair (at most 0.4 s of one thread): a grid would not pay."""
CHUNK_POINTS = 256
"""Points of one grid query: consecutive in the grid's Z-order, so a compact block of cells."""
BRUTE_FORCE_ROWS = 512
"""Points left uncertain by a grid that take every pair rather than another, coarser grid."""
SAMPLE_POINTS = 1024
"""Points whose exact distances choose the grid's cell size."""


def _pair_distances(rows: Tensor, points: Tensor) -> Tensor:
    """Euclidean distances [R, P] from the coordinates' differences: cdist's default for large inputs,
    |a|^2 + |b|^2 - 2 a.b by a matrix product, cancels to the rounding of |a|^2 when the neighbours
    are close next to the distance from the origin (a unit cube of 5000 points at (100, 100, 100):
    mean distances off by up to 0.065 where they are 0.043, a quarter of them 0), and a cloud far from
    its origin is what a georeferenced capture gives."""
    return torch.cdist(rows, points, compute_mode="donot_use_mm_for_euclid_dist")


def _nearest_brute(rows: Tensor, points: Tensor, k: int, chunk: int) -> Tensor:
    """The k + 1 smallest distances [R, k + 1] from each row to every point (its own 0 first)."""
    out = []
    for start in range(0, rows.shape[0], chunk):
        d = _pair_distances(rows[start:start + chunk], points)
        out.append(torch.topk(d, k + 1, dim=1, largest=False).values)
    return torch.cat(out) if out else rows.new_zeros((0, k + 1))


def every_pair_mean_distance(points: Tensor, k: int = 3, chunk: int = 2048) -> Tensor:
    """Mean distance [P] of each point to its k nearest other points (P > k), from every pair: the
    reference the grid gives the bits of, and the path of small clouds."""
    return _nearest_brute(points, points, k, chunk)[:, 1:].mean(dim=1)


def _spread_bits(v: Tensor) -> Tensor:
    """The low 21 bits of v (int64) moved to every third bit: one axis of a 3-D Morton code."""
    v = v & 0x1FFFFF
    v = (v | (v << 32)) & 0x1F00000000FFFF
    v = (v | (v << 16)) & 0x1F0000FF0000FF
    v = (v | (v << 8)) & 0x100F00F00F00F00F
    v = (v | (v << 4)) & 0x10C30C30C30C30C3
    v = (v | (v << 2)) & 0x1249249249249249
    return v


def _nearest_in_grid(points: Tensor, pending: Tensor, cell: float, k: int) -> tuple[Tensor, Tensor]:
    """For the points ``pending`` (indices), the k + 1 smallest distances to every point, found in
    the cells around them, and whether each is certain: the (k+1)-th is nearer than any point
    outside the cells searched. Returns (values [R, k + 1], certain [R]) in the order of ``pending``."""
    origin = points.min(dim=0).values
    cells = torch.floor((points - origin) / cell).to(torch.int64)  # [P, 3]
    # Z-order of the pending points: consecutive ones fill compact blocks of cells
    mine = cells[pending]
    morton = _spread_bits(mine[:, 0]) | (_spread_bits(mine[:, 1]) << 1) | (_spread_bits(mine[:, 2]) << 2)
    order = pending[torch.argsort(morton, stable=True)]
    # A point outside the searched cells lies at least this far beyond their faces' computed
    # position: the coordinates' rounding in (p - origin) / cell, with room to spare.
    slack = 1e-4 * cell + 8 * torch.finfo(points.dtype).eps * float(points.abs().max())
    values, certain = [], []
    for start in range(0, order.shape[0], CHUNK_POINTS):
        rows = order[start:start + CHUNK_POINTS]
        low = cells[rows].min(dim=0).values - 1
        high = cells[rows].max(dim=0).values + 1
        near = ((cells >= low) & (cells <= high)).all(dim=1).nonzero().squeeze(1)
        if near.shape[0] < k + 1:  # fewer points in the cells than neighbours asked for
            values.append(torch.zeros(rows.shape[0], k + 1, dtype=points.dtype, device=points.device))
            certain.append(torch.zeros(rows.shape[0], dtype=torch.bool, device=points.device))
            continue
        nearest = torch.topk(_pair_distances(points[rows], points[near]), k + 1, dim=1, largest=False).values
        # distance from each point to the faces of the searched block, less the slack
        face_low = origin + low.to(points.dtype) * cell
        face_high = origin + (high + 1).to(points.dtype) * cell
        p = points[rows]
        margin = torch.minimum(p - face_low, face_high - p).min(dim=1).values - slack
        values.append(nearest)
        certain.append(nearest[:, k] < margin)
    # from Z-order back to the order of ``pending``
    position = torch.full((points.shape[0],), -1, dtype=torch.int64, device=points.device)
    position[pending] = torch.arange(pending.shape[0], device=points.device)
    back = position[order]
    out_values = torch.empty(pending.shape[0], k + 1, dtype=points.dtype, device=points.device)
    out_certain = torch.empty(pending.shape[0], dtype=torch.bool, device=points.device)
    out_values[back] = torch.cat(values)
    out_certain[back] = torch.cat(certain)
    return out_values, out_certain


def knn_mean_distance(points: Tensor, k: int = 3, chunk: int = 2048) -> Tensor:
    """Mean distance of each point to its k nearest other points. points: [P, 3] -> [P].

    Coincident points give 0 distance; callers floor it. Below ``BRUTE_FORCE_BELOW`` points every
    pair, in chunks of ``chunk`` rows (memory O(chunk x P)); above, a grid whose cell is twice the
    median (k+1)-th neighbour's distance of a sample of points: each point is searched in the
    cells around it, and the few whose neighbours may lie beyond those cells (the isolated ones)
    again in a grid of twice the cell, until every point is certain or what is left takes every
    pair. The same bits as every pair, at any size (tests/test_model_init.py).
    """
    n = points.shape[0]
    if n <= 1:
        return torch.ones(n, dtype=points.dtype, device=points.device)
    k_eff = min(k, n - 1)
    if n < BRUTE_FORCE_BELOW:
        return every_pair_mean_distance(points, k_eff, chunk)
    # the sample's neighbours, from every pair, are final: they choose the cell and are not searched again
    sampled = torch.linspace(0, n - 1, SAMPLE_POINTS, device=points.device).long()  # distinct: n > SAMPLE_POINTS
    sample_nearest = _nearest_brute(points[sampled], points, k_eff, chunk)
    extent = float((points.max(dim=0).values - points.min(dim=0).values).max())
    # twice the sample's median reach: most points are certain in the first grid, and the cells
    # stay small where the cloud is dense (a 90% quantile took 2.4 times as long on random points
    # along the training rays, whose spacing spreads far)
    cell = 2.0 * float(torch.quantile(sample_nearest[:, k_eff].double(), 0.5))
    if not cell > 0 or not extent > 0:  # most of the cloud coincides: every pair decides
        return every_pair_mean_distance(points, k_eff, chunk)
    nearest = torch.empty(n, k_eff + 1, dtype=points.dtype, device=points.device)
    nearest[sampled] = sample_nearest
    searched = torch.ones(n, dtype=torch.bool, device=points.device)
    searched[sampled] = False
    pending = searched.nonzero().squeeze(1)
    while pending.numel() > 0:
        if pending.numel() < BRUTE_FORCE_ROWS or cell > extent:  # few left, or the grid is one cell
            nearest[pending] = _nearest_brute(points[pending], points, k_eff, chunk)
            break
        values, certain = _nearest_in_grid(points, pending, cell, k_eff)
        nearest[pending[certain]] = values[certain]
        pending = pending[~certain]
        cell *= 2.0
    return nearest[:, 1:].mean(dim=1)
