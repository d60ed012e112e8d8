"""Tile binning: one depth sort, one stable sort of tile-Gaussian pairs, chunks of tiles."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor


@dataclass
class TileBins:
    """Tile-Gaussian pairs sorted by tile, then by depth within each tile.

    ``gauss_ids`` index the rows given to :func:`bin_gaussians` (the visible subset).
    """

    gauss_ids: Tensor
    """[P] int64 Gaussian row of every pair, grouped by tile, front to back inside a tile."""
    tile_offsets: Tensor
    """[T] int64 first pair of each tile."""
    tile_counts: Tensor
    """[T] int64 number of pairs of each tile."""
    tiles_x: int
    tiles_y: int
    tile_size: int
    width: int = 0
    """Image width in pixels (tiles on the right edge may reach past it)."""
    height: int = 0
    """Image height in pixels."""

    @property
    def n_pairs(self) -> int:
        return int(self.gauss_ids.numel())

    @property
    def n_tiles(self) -> int:
        return self.tiles_x * self.tiles_y


def bin_gaussians(
    means2d: Tensor, support: Tensor, depths: Tensor, width: int, height: int, tile_size: int
) -> TileBins:
    """Pairs every Gaussian with the tiles its support box touches.

    means2d: [M, 2] pixels; support: [M, 2] half-widths; depths: [M]. All detached.
    The box holds pixel centres i + 0.5 with |i + 0.5 - mean| <= half-width; the tile range is
    widened by 1e-3 px so that rounding never drops a tile (the compositor tests every pixel).
    """
    tiles_x = (width + tile_size - 1) // tile_size
    tiles_y = (height + tile_size - 1) // tile_size
    n_tiles = tiles_x * tiles_y
    dev = means2d.device
    if means2d.shape[0] == 0:
        empty = torch.zeros(0, dtype=torch.int64, device=dev)
        zeros = torch.zeros(n_tiles, dtype=torch.int64, device=dev)
        return TileBins(empty, zeros, zeros.clone(), tiles_x, tiles_y, tile_size, width, height)
    size = torch.tensor([width - 1, height - 1], dtype=means2d.dtype, device=dev)
    lo = torch.ceil(means2d - support - 0.5 - 1e-3).clamp(min=0).minimum(size)
    hi = torch.floor(means2d + support - 0.5 + 1e-3).clamp(min=0).minimum(size)
    t_lo = lo.long() // tile_size  # [M, 2]
    t_hi = hi.long() // tile_size
    n_xy = t_hi - t_lo + 1
    counts = n_xy[:, 0] * n_xy[:, 1]

    order = torch.argsort(depths, stable=True)  # pairs are generated front to back
    counts_o = counts[order]
    total = int(counts_o.sum())
    gid = torch.repeat_interleave(order, counts_o)
    starts = torch.cumsum(counts_o, 0) - counts_o
    local = torch.arange(total, device=dev) - torch.repeat_interleave(starts, counts_o)
    nx = n_xy[gid, 0]
    tile = (t_lo[gid, 1] + local // nx) * tiles_x + t_lo[gid, 0] + local % nx
    # A stable sort by tile keeps the depth order inside every tile.
    tile_sorted, perm = torch.sort(tile, stable=True)
    tile_counts = torch.bincount(tile_sorted, minlength=n_tiles)
    tile_offsets = torch.cumsum(tile_counts, 0) - tile_counts
    return TileBins(gid[perm], tile_offsets, tile_counts, tiles_x, tiles_y, tile_size, width, height)


def plan_chunks(bins: TileBins, chunk_elements: int) -> list[tuple[Tensor, int]]:
    """Groups non-empty tiles into chunks of about ``chunk_elements`` pixel-pair evaluations.

    Tiles are taken in order of decreasing pair count, so padding each chunk to its largest
    tile wastes little. Returns (tile ids [B] int64, padded pair count K) per chunk.
    """
    counts = bins.tile_counts
    order = torch.argsort(counts, descending=True, stable=True)
    sorted_counts = counts[order].tolist()
    pixels = bins.tile_size * bins.tile_size
    chunks: list[tuple[Tensor, int]] = []
    n_nonempty = sum(1 for c in sorted_counts if c > 0)
    i = 0
    while i < n_nonempty:
        k = sorted_counts[i]
        j = min(n_nonempty, i + max(1, chunk_elements // (pixels * k)))
        chunks.append((order[i:j], k))
        i = j
    return chunks


def gather_table(bins: TileBins, tiles: Tensor, k: int, pad_index: int) -> Tensor:
    """Padded [B, K] table of Gaussian rows for the given tiles; missing entries = ``pad_index``."""
    ar = torch.arange(k, device=tiles.device)
    idx = bins.tile_offsets[tiles][:, None] + ar[None, :]
    valid = ar[None, :] < bins.tile_counts[tiles][:, None]
    idx = torch.where(valid, idx, torch.zeros_like(idx))
    return torch.where(valid, bins.gauss_ids[idx], torch.full_like(idx, pad_index))
