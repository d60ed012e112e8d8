"""Front-to-back alpha compositing over tiles, as one custom autograd Function.

Work is done in chunks of whole tiles: a chunk gathers its tiles' pairs into a padded
[B, K] table and evaluates [B, tile_size^2, K] pixel-pair tensors small enough to stay in
cache. The forward keeps nothing per pair (only the largest contributor count of each chunk);
the backward recomputes each chunk's alphas and transmittances and forms the exact derivative
with a suffix sum, so no [pixels x Gaussians] intermediate outlives its chunk.

Per pixel, with Gaussians m = 1..n front to back (only pairs inside the support box):
    alpha_m = min(alpha_max, o_m exp(power_m)),  power_m = -0.5 (a dx^2 + 2 b dx dy + c dy^2),
    pairs with alpha_m < alpha_min are skipped (alpha_m := 0),
    T_m = prod_{j<m} (1 - alpha_j),  compositing stops before the first m with T_{m+1} < T_min,
    F = sum_m w_m f_m with w_m = alpha_m T_m  (f = colour, depth, and 1 for the alpha A = 1 - T_final).
Derivative, with S_m = sum_{i>m} w_i (dL/dF . f_i):
    dL/dalpha_m = T_m (dL/dF . f_m) - S_m / (1 - alpha_m),
    dL/dpower_m = alpha_m dL/dalpha_m = w_m (dL/dF . f_m) - S_m alpha_m / (1 - alpha_m),
zero where the clamp is active and for pairs after the stop.

Speed notes (measured per element on these CPUs): exp2 is ~3x cheaper than exp, boolean masks
(masked_fill, where) ~30x dearer than arithmetic, and bmm wants its thin operand column-major;
so masks are arithmetic (threshold, sign), exp is exp2 with log2(e) folded into the conic,
and feature tables are kept as [B, F, K].
"""

from __future__ import annotations

import math
import os
import threading
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager

import torch
from torch import Tensor

from .settings import RasterSettings
from .tiling import TileBins, gather_table, plan_chunks

LOG2E = 1.4426950408889634
# Columns of the per-Gaussian geometry table gathered per chunk.
_MX, _MY, _A, _B, _C, _O, _LOG2O, _RX, _RY = range(9)
_NGEOM = 9
# Exponent penalty (log2 units) per pixel of distance outside the support box: a pixel
# outside by more than ~1e-28 px gets alpha exactly 0.
_OUTSIDE = 1e30

_POOL: ThreadPoolExecutor | None = None
_POOL_LOCK = threading.Lock()


def _pool(workers: int) -> ThreadPoolExecutor:
    global _POOL
    with _POOL_LOCK:
        if _POOL is None or _POOL._max_workers < workers:
            _POOL = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="eg-raster")
        return _POOL


@contextmanager
def single_threaded_ops():
    """Runs torch ops single-threaded inside the block (restores the caller's setting).

    Measured on 2-core machines shared with other processes: OpenMP barriers in parallel ops
    cost far more than they save on the small O(N) tensors of the projection, and the
    compositing workers below each own one core instead.
    """
    saved = torch.get_num_threads()
    if saved != 1:
        torch.set_num_threads(1)
    try:
        yield
    finally:
        if saved != 1:
            torch.set_num_threads(saved)


def _run_split(fn, n_items: int, workers: int) -> list:
    """Runs fn(worker_id, item_ids) with items dealt round-robin, torch ops single-threaded."""
    workers = max(1, min(workers, n_items))
    parts = [list(range(w, n_items, workers)) for w in range(workers)]
    with single_threaded_ops():
        if workers == 1:
            return [fn(0, parts[0])]
        futs = [_pool(workers).submit(fn, w, parts[w]) for w in range(1, workers)]
        first = fn(0, parts[0])
        return [first] + [f.result() for f in futs]


def _pixel_offsets(tile_size: int, dtype: torch.dtype) -> Tensor:
    """Pixel-centre coordinates relative to the tile centre: [tile_size] (e.g. -7.5 .. 7.5)."""
    return torch.arange(tile_size, dtype=dtype) + 0.5 - 0.5 * tile_size


def _moment_features(tile_size: int, dtype: torch.dtype) -> Tensor:
    """[6, P] rows 1, x, y, x^2, x y, y^2 over the tile's pixels (row-major, y outer)."""
    p = _pixel_offsets(tile_size, dtype)
    y, x = torch.meshgrid(p, p, indexing="ij")
    x, y = x.reshape(-1), y.reshape(-1)
    return torch.stack([torch.ones_like(x), x, y, x * x, x * y, y * y])


class _Chunk:
    """One chunk's gathered pairs: geometry [B, K, 9], features [B, F+1, K], means relative to
    tile centres [B, K]."""

    def __init__(self, geom: Tensor, feat_t: Tensor, bins: TileBins, tiles: Tensor, k: int):
        m = geom.shape[0] - 1
        self.gidx = gather_table(bins, tiles, k, m).reshape(-1)  # [B*K]
        bsz = len(tiles)
        self.g = geom.index_select(0, self.gidx).view(bsz, k, -1)
        # [F+1, B*K] -> [B, F+1, K]: bmm reads this "column-major" operand fastest
        self.f = feat_t.index_select(1, self.gidx).view(-1, bsz, k).transpose(0, 1).contiguous()
        ts = bins.tile_size
        dtype = geom.dtype
        cx = (tiles % bins.tiles_x).to(dtype) * ts + 0.5 * ts
        cy = (tiles // bins.tiles_x).to(dtype) * ts + 0.5 * ts
        self.mxr = self.g[..., _MX] - cx[:, None]
        self.myr = self.g[..., _MY] - cy[:, None]
        self.bsz, self.k = bsz, k


def _chunk_alpha(c: _Chunk, pix: Tensor, s: RasterSettings) -> Tensor:
    """Alphas of a chunk after clamp and skip: [B, P, K].

    Through the Cholesky factor of the conic, 0.5 log2(e) q = u^2 + v^2 with
    u = l11 dx + l21 dy and v = l22 dy, and alpha = exp2(log2 o - u^2 - v^2). With
    u = ux + uy (ux = l11 dx per column, uy = l21 dy per row) the exponent is
    [log2 o - ux^2] + [-uy^2 - v^2] - 2 ux uy: two per-column/per-row terms and one outer
    product, so only two passes touch the [B, P, K] tensor before exp2.
    Pixels outside the support box get -inf (alpha 0).
    """
    g = c.g
    h = 0.5 * LOG2E
    l11 = torch.sqrt(h * g[..., _A].clamp_min(1e-30))
    l21 = h * g[..., _B] / l11
    l22sq = (h * g[..., _C] - l21 * l21).clamp_min(0.0)
    dx = pix[None, :, None] - c.mxr[:, None, :]  # [B, S, K] (columns)
    dy = pix[None, :, None] - c.myr[:, None, :]  # [B, S, K] (rows)
    ux = l11[:, None, :] * dx
    uy = l21[:, None, :] * dy
    # 0 inside the box, <= -1e30 * distance outside (exp2 -> 0); arithmetic, not a boolean mask
    out_x = (g[:, None, :, _RX] - dx.abs()).clamp_max_(0.0).mul_(_OUTSIDE)
    out_y = (g[:, None, :, _RY] - dy.abs()).clamp_max_(0.0).mul_(_OUTSIDE)
    col = (g[:, None, :, _LOG2O] - ux * ux).add_(out_x)
    row = (uy * uy).addcmul_(l22sq[:, None, :], dy * dy).neg_().add_(out_y)
    arg = row[:, :, None, :] + col[:, None, :, :]  # [B, S, S, K]
    arg.addcmul_(uy[:, :, None, :], ux[:, None, :, :], value=-2.0)
    alpha = arg.exp2_().clamp_max_(s.alpha_max)
    # keep alpha >= alpha_min: threshold keeps values strictly above its argument
    torch.nn.functional.threshold_(alpha, math.nextafter(s.alpha_min, 0.0), 0.0)
    return alpha.view(c.bsz, -1, c.k)


def _transmittance(alpha: Tensor, s: RasterSettings) -> tuple[Tensor, Tensor]:
    """T before each pair [B, P, K] and the inclusion indicator [B, P, K] (1 until the stop, then 0).

    A pair is included when the transmittance after it stays >= T_min; T only decreases, so the
    excluded pairs form a suffix.
    """
    bsz, p, k = alpha.shape
    tb = alpha.new_empty(bsz, p, k + 1)
    tb[..., 0] = 1.0
    torch.sub(alpha.new_ones(()), alpha, out=tb[..., 1:])
    tb.cumprod_(-1)
    keep = torch.nn.functional.threshold(tb[..., 1:], math.nextafter(s.transmittance_min, 0.0), 0.0).sign_()
    return tb[..., :-1], keep


def _forward_chunks(geom, feat_t, bins, chunks, ids, s, out, used):
    pix = _pixel_offsets(bins.tile_size, geom.dtype)
    for i in ids:
        tiles, k = chunks[i]
        c = _Chunk(geom, feat_t, bins, tiles, k)
        alpha = _chunk_alpha(c, pix, s)
        t_before, keep = _transmittance(alpha, s)
        used[i] = int(keep.sum(-1).max())
        w = alpha.mul_(t_before).mul_(keep)
        out[tiles] = torch.bmm(w, c.f.transpose(1, 2))


def _backward_chunks(geom, feat_t, bins, chunks, used, ids, s, grad_out, nf) -> Tensor:
    dtype = geom.dtype
    pix = _pixel_offsets(bins.tile_size, dtype)
    fm = _moment_features(bins.tile_size, dtype)  # [6, P]
    gbuf = torch.zeros(geom.shape[0], 6 + nf, dtype=dtype)  # d mx, my, a, b, c, o, features
    for i in ids:
        tiles, _ = chunks[i]
        if used[i] == 0:
            continue
        c = _Chunk(geom, feat_t, bins, tiles, used[i])
        alpha = _chunk_alpha(c, pix, s)
        t_before, keep = _transmittance(alpha, s)
        free = torch.lt(alpha, s.alpha_max, out=torch.empty_like(alpha))  # clamp inactive: 1, else 0
        odds = alpha / torch.rsub(alpha, 1.0)
        odds.mul_(keep).mul_(free)
        w = alpha.mul_(t_before).mul_(keep)
        gpix = grad_out.index_select(0, tiles)  # [B, P, F+1]
        gf = torch.bmm(gpix, c.f)  # [B, P, K] = dL/dF . f_m
        dfeat = torch.bmm(gpix.transpose(1, 2).contiguous(), w)  # [B, F+1, K]
        wg = gf.mul_(w)
        suffix = wg.cumsum(-1)
        suffix = torch.sub(suffix[..., -1:], suffix).mul_(odds)  # S_m alpha_m / (1 - alpha_m)
        g_power = wg.mul_(free).sub_(suffix)
        mom = torch.matmul(fm, g_power)  # [B, 6, K]: sums of g_power * (1, x, y, x^2, xy, y^2)
        s0, s1, s2, s3, s4, s5 = mom.unbind(1)
        mxr, myr = c.mxr, c.myr
        sdx = s1 - mxr * s0
        sdy = s2 - myr * s0
        sdxx = s3 - 2.0 * mxr * s1 + mxr * mxr * s0
        sdxy = s4 - mxr * s2 - myr * s1 + mxr * myr * s0
        sdyy = s5 - 2.0 * myr * s2 + myr * myr * s0
        ca, cb, cc = c.g[..., _A], c.g[..., _B], c.g[..., _C]
        pair = torch.stack(
            [
                ca * sdx + cb * sdy,  # dpower/dmx = a dx + b dy
                cb * sdx + cc * sdy,  # dpower/dmy = b dx + c dy
                -0.5 * sdxx,
                -sdxy,
                -0.5 * sdyy,
                s0 / c.g[..., _O].clamp_min(1e-30),  # dalpha/do = alpha / o
            ],
            dim=-1,
        )
        rows = torch.cat([pair, dfeat[:, :nf].transpose(1, 2)], -1).reshape(c.bsz * c.k, -1)
        gbuf.index_add_(0, c.gidx, rows)
    return gbuf


def available_cpus() -> int:
    """CPUs this process may run on."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


def _workers(s: RasterSettings) -> int:
    return s.workers if s.workers > 0 else available_cpus()


class _Composite(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, opacities, feats, support, bins, settings):  # type: ignore[override]
        dtype = means2d.dtype
        nf = feats.shape[1]
        geom, feat_t = _tables(means2d, conics, opacities, support, feats)
        npix = bins.tile_size**2
        out = torch.zeros(bins.n_tiles, npix, nf + 1, dtype=dtype)
        chunks = plan_chunks(bins, settings.chunk_elements)
        used = [0] * len(chunks)
        _run_split(
            lambda _, ids: _forward_chunks(geom, feat_t, bins, chunks, ids, settings, out, used),
            len(chunks), _workers(settings),
        )  # fmt: skip
        ctx.save_for_backward(geom, feat_t)
        ctx.chunks, ctx.used, ctx.bins, ctx.settings, ctx.nf = chunks, used, bins, settings, nf
        return out

    @staticmethod
    def backward(ctx, grad_out):  # type: ignore[override]
        geom, feat_t = ctx.saved_tensors
        grad_out = grad_out.contiguous()
        parts = _run_split(
            lambda _, ids: _backward_chunks(
                geom, feat_t, ctx.bins, ctx.chunks, ctx.used, ids, ctx.settings, grad_out, ctx.nf
            ),
            len(ctx.chunks), _workers(ctx.settings),
        )  # fmt: skip
        gbuf = parts[0]
        for p in parts[1:]:
            gbuf += p
        gbuf = gbuf[:-1]
        return gbuf[:, 0:2], gbuf[:, 2:5], gbuf[:, 5], gbuf[:, 6:], None, None, None


def _tables(means2d: Tensor, conics: Tensor, opacities: Tensor, support: Tensor, feats: Tensor) -> tuple[Tensor, Tensor]:
    """Per-Gaussian geometry [M + 1, 9] and transposed features [F + 1, M + 1] (a last row of
    ones for the alpha). The extra last Gaussian is the padding entry (never drawn)."""
    o = opacities[:, None]
    geom = torch.cat([means2d, conics, o, torch.log2(o), support], -1)
    pad = torch.zeros(1, geom.shape[1], dtype=geom.dtype)
    pad[0, _LOG2O] = -math.inf
    pad[0, _RX] = pad[0, _RY] = -1.0  # |dx| <= -1 never holds
    pad[0, _A] = pad[0, _C] = 1.0
    geom = torch.cat([geom, pad], 0).detach()
    feat_t = torch.cat([feats, torch.ones_like(feats[:, :1])], -1).detach()
    feat_t = torch.cat([feat_t, torch.zeros_like(feat_t[:1])], 0).T.contiguous()
    return geom, feat_t


def composite(
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    feats: Tensor,
    support: Tensor,
    bins: TileBins,
    settings: RasterSettings,
) -> Tensor:
    """Composites the binned Gaussians.

    means2d: [M, 2]; conics: [M, 3]; opacities: [M]; feats: [M, F] (colour, depth, ...);
    support: [M, 2] box half-widths (no gradient). Returns [T, tile_size^2, F + 1]: the
    composited features and, last, the accumulated alpha sum_m w_m = 1 - T_final, per tile pixel.
    """
    return _Composite.apply(means2d, conics, opacities, feats, support.detach(), bins, settings)
