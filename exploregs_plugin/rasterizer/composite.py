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

Speed notes (per-element costs from `python -m exploregs_plugin.bench.components.opcost`): exp2 is
~3x cheaper than exp, boolean masks (masked_fill, where) ~25x dearer than arithmetic, and bmm
wants its thin operand column-major; so masks are arithmetic (threshold, sign), exp is exp2
with log2(e) folded into the conic, and feature tables are kept as [B, F, K].
"""

from __future__ import annotations

import math
import threading
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager

import torch
from torch import Tensor

from .settings import VISIBILITY_COLUMNS, VISIBILITY_PEAK, RasterSettings
from .tiling import TileBins, gather_table, plan_chunks

LOG2E = 1.4426950408889634
# Columns of the per-Gaussian geometry table gathered per chunk.
_MX, _MY, _A, _B, _C, _O, _LOG2O, _RX, _RY, _L11, _L21, _L22SQ = range(12)
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


_THREADS_LOCK = threading.Lock()
_THREADS_STATE = {"depth": 0, "saved": 1}


def enter_single_threaded() -> None:
    """Makes torch ops single-threaded until the matching :func:`exit_single_threaded`.

    Nested and concurrent callers (a viewer thread rendering beside training) share one counter,
    so the caller's thread count is restored exactly once, when the last one leaves.
    """
    with _THREADS_LOCK:
        if _THREADS_STATE["depth"] == 0:
            _THREADS_STATE["saved"] = torch.get_num_threads()
            if _THREADS_STATE["saved"] != 1:
                torch.set_num_threads(1)
        _THREADS_STATE["depth"] += 1


def exit_single_threaded() -> None:
    with _THREADS_LOCK:
        _THREADS_STATE["depth"] -= 1
        if _THREADS_STATE["depth"] == 0 and _THREADS_STATE["saved"] != 1:
            torch.set_num_threads(_THREADS_STATE["saved"])


def single_threaded_now() -> bool:
    """Whether some caller holds torch ops single-threaded (:func:`single_threaded_ops`: a CPU
    run's whole training step)."""
    with _THREADS_LOCK:
        return _THREADS_STATE["depth"] > 0


@contextmanager
def single_threaded_ops():
    """Runs torch ops single-threaded inside the block (restores the caller's setting).

    Measured on 2-core machines shared with other processes: OpenMP barriers in parallel ops
    cost far more than they save on the small O(N) tensors of the projection, and the
    compositing workers below each own one core instead.
    """
    enter_single_threaded()
    try:
        yield
    finally:
        exit_single_threaded()


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


def _pixel_offsets(tile_size: int, dtype: torch.dtype, device: torch.device) -> Tensor:
    """Pixel-centre coordinates relative to the tile centre: [tile_size] (e.g. -7.5 .. 7.5)."""
    return torch.arange(tile_size, dtype=dtype, device=device) + 0.5 - 0.5 * tile_size


def _moment_features(tile_size: int, dtype: torch.dtype, device: torch.device) -> Tensor:
    """[6, P] rows 1, x, y, x^2, x y, y^2 over the tile's pixels (row-major, y outer)."""
    p = _pixel_offsets(tile_size, dtype, device)
    y, x = torch.meshgrid(p, p, indexing="ij")
    x, y = x.reshape(-1), y.reshape(-1)
    return torch.stack([torch.ones_like(x), x, y, x * x, x * y, y * y])


class _Chunk:
    """One chunk's gathered pairs (made in the forward, reused by the backward).

    g: [B, K, 12] geometry; f: [B, F+1, K] features; mxr, myr: [B, K] means relative to the
    tile centres; gidx: [B, K] Gaussian rows (the padding row for missing pairs).
    """

    def __init__(self, g: Tensor, f: Tensor, mxr: Tensor, myr: Tensor, gidx: Tensor, tiles: Tensor):
        self.g, self.f, self.mxr, self.myr, self.gidx, self.tiles = g, f, mxr, myr, gidx, tiles

    @staticmethod
    def gather(geom: Tensor, feat_t: Tensor, bins: TileBins, tiles: Tensor, k: int) -> "_Chunk":
        bsz = len(tiles)
        gidx = gather_table(bins, tiles, k, geom.shape[0] - 1)  # [B, K]
        flat = gidx.reshape(-1)
        g = geom.index_select(0, flat).view(bsz, k, -1)
        # [F+1, B*K] -> [B, F+1, K]: bmm reads this "column-major" operand fastest
        f = feat_t.index_select(1, flat).view(-1, bsz, k).transpose(0, 1).contiguous()
        ts = bins.tile_size
        cx = (tiles % bins.tiles_x).to(geom.dtype) * ts + 0.5 * ts
        cy = (tiles // bins.tiles_x).to(geom.dtype) * ts + 0.5 * ts
        return _Chunk(g, f, g[..., _MX] - cx[:, None], g[..., _MY] - cy[:, None], gidx, tiles)

    def first(self, k: int) -> "_Chunk":
        """The first k pairs of every tile (pairs behind every pixel's stop do not matter)."""
        return _Chunk(self.g[:, :k], self.f[..., :k], self.mxr[:, :k], self.myr[:, :k], self.gidx[:, :k], self.tiles)


def _chunk_alpha(g: Tensor, mxr: Tensor, myr: Tensor, pix: Tensor, alpha_max: float, alpha_keep: float) -> Tensor:
    """Alphas of a chunk after clamp and skip: [B, P, K].

    g: [B, K, 12] gathered geometry; mxr, myr: [B, K] means relative to the tile centre;
    pix: [S] pixel offsets; alpha values <= ``alpha_keep`` are skipped (set to 0).
    Through the Cholesky factor of the conic, 0.5 log2(e) q = u^2 + v^2 with
    u = l11 dx + l21 dy and v = l22 dy, and alpha = exp2(log2 o - u^2 - v^2). With
    u = ux + uy (ux = l11 dx per column, uy = l21 dy per row) the exponent is
    [log2 o - ux^2] + [-uy^2 - v^2] - 2 ux uy: two per-column/per-row terms and one outer
    product, so only two passes touch the [B, P, K] tensor before exp2.
    Pixels outside the support box get -inf (alpha 0).
    """
    bsz, k = mxr.shape
    l11, l21, l22sq = g[..., _L11], g[..., _L21], g[..., _L22SQ]
    dx = pix[None, :, None] - mxr[:, None, :]  # [B, S, K] (columns)
    dy = pix[None, :, None] - myr[:, None, :]  # [B, S, K] (rows)
    ux = l11[:, None, :] * dx
    uy = l21[:, None, :] * dy
    # 0 inside the box, <= -1e30 * distance outside (exp2 -> 0); arithmetic, not a boolean mask
    out_x = (g[:, None, :, _RX] - dx.abs()).clamp_max_(0.0).mul_(_OUTSIDE)
    out_y = (g[:, None, :, _RY] - dy.abs()).clamp_max_(0.0).mul_(_OUTSIDE)
    col = (g[:, None, :, _LOG2O] - ux * ux).add_(out_x)
    row = (uy * uy).addcmul_(l22sq[:, None, :], dy * dy).neg_().add_(out_y)
    arg = row[:, :, None, :] + col[:, None, :, :]  # [B, S, S, K]
    arg.addcmul_(uy[:, :, None, :], ux[:, None, :, :], value=-2.0)
    alpha = arg.exp2_().clamp_max_(alpha_max)
    # threshold keeps values strictly above its argument
    torch.nn.functional.threshold_(alpha, alpha_keep, 0.0)
    return alpha.view(bsz, -1, k)


def _transmittance(alpha: Tensor, t_keep: float) -> tuple[Tensor, Tensor]:
    """T before each pair [B, P, K] and the inclusion indicator [B, P, K] (1 until the stop, then 0).

    A pair is included when the transmittance after it stays above ``t_keep``; T only
    decreases, so the excluded pairs form a suffix.
    """
    bsz, p, k = alpha.shape
    tb = alpha.new_empty(bsz, p, k + 1)
    tb[..., 0] = 1.0
    torch.sub(alpha.new_ones(()), alpha, out=tb[..., 1:])  # one pass, no padded copy
    tb.cumprod_(-1)
    keep = torch.nn.functional.threshold(tb[..., 1:], t_keep, 0.0).sign_()
    return tb[..., :-1], keep


def _forward_kernel(g, mxr, myr, pix, alpha_max: float, alpha_keep: float, t_keep: float,
                    inside: Tensor | None = None):
    """Compositing weights w = alpha T (0 after the stop) [B, P, K], the largest number of
    included pairs of any pixel (a 0-d tensor) and, given ``inside`` ([B, P, 1] pixel mask),
    each pair's included alpha summed over the tile's pixels inside the image [B, K] (else None)."""
    alpha = _chunk_alpha(g, mxr, myr, pix, alpha_max, alpha_keep)
    t_before, keep = _transmittance(alpha, t_keep)
    summed = (alpha * keep * inside).sum(1) if inside is not None else None
    return alpha.mul_(t_before).mul_(keep), keep.sum(-1).amax(), summed


def _backward_kernel(g, mxr, myr, pix, gf, alpha_max: float, alpha_keep: float, t_keep: float):
    """Recomputes the weights w [B, P, K] and returns them with dL/dpower [B, P, K], given
    gf = dL/dF . f_m [B, P, K] (overwritten)."""
    alpha = _chunk_alpha(g, mxr, myr, pix, alpha_max, alpha_keep)
    t_before, keep = _transmittance(alpha, t_keep)
    free = torch.lt(alpha, alpha_max, out=torch.empty_like(alpha))  # clamp inactive: 1, else 0
    odds = (alpha / (1.0 - alpha)).mul_(keep).mul_(free)
    w = alpha.mul_(t_before).mul_(keep)
    wg = gf.mul_(w)
    suffix = wg.cumsum(-1)
    suffix = (suffix[..., -1:] - suffix).mul_(odds)  # S_m alpha_m / (1 - alpha_m)
    return w, wg.mul_(free).sub_(suffix)


def _thresholds(s: RasterSettings) -> tuple[float, float, float]:
    """(alpha_max, alpha_keep, t_keep): keep alpha >= alpha_min and T >= T_min as strict '>'."""
    return s.alpha_max, math.nextafter(s.alpha_min, 0.0), math.nextafter(s.transmittance_min, 0.0)


def _inside_image(bins: TileBins, tiles: Tensor, dtype: torch.dtype) -> Tensor:
    """[B, P, 1]: 1 for the tiles' pixels inside the image, 0 for those past its right or bottom edge."""
    ts = bins.tile_size
    offs = torch.arange(ts, device=tiles.device)
    px = (tiles % bins.tiles_x)[:, None] * ts + offs[None, :]  # [B, ts] columns
    py = (tiles // bins.tiles_x)[:, None] * ts + offs[None, :]  # [B, ts] rows
    inside = (py[:, :, None] < bins.height) & (px[:, None, :] < bins.width)  # [B, ts (y), ts (x)]
    return inside.reshape(len(tiles), ts * ts, 1).to(dtype)


def _forward_chunks(geom, feat_t, bins, chunks, ids, s, out, used, cache) -> Tensor | None:
    """Composites chunks ``ids`` into ``out``; with ``s.visibility_stats``, returns this worker's
    per-Gaussian [M + 1, 3]: the sums of the weight alpha T and of alpha over its pixels, and the
    largest weight (``VISIBILITY_COLUMNS``)."""
    pix = _pixel_offsets(bins.tile_size, geom.dtype, geom.device)
    stats = torch.zeros(geom.shape[0], len(VISIBILITY_COLUMNS), dtype=geom.dtype, device=geom.device) \
        if s.visibility_stats else None
    for i in ids:
        tiles, k = chunks[i]
        c = _Chunk.gather(geom, feat_t, bins, tiles, k)
        inside = _inside_image(bins, tiles, geom.dtype) if stats is not None else None  # padding counts nothing
        w, n_used, alpha_sum = _forward_kernel(c.g, c.mxr, c.myr, pix, *_thresholds(s), inside=inside)
        used[i] = int(n_used)
        out[tiles] = torch.bmm(w, c.f.transpose(1, 2))
        if stats is not None:
            rows = c.gidx.reshape(-1)
            w_inside = w * inside
            stats[:, 0].index_add_(0, rows, w_inside.sum(1).reshape(-1))
            stats[:, 1].index_add_(0, rows, alpha_sum.reshape(-1))
            stats[:, 2].scatter_reduce_(0, rows, w_inside.amax(1).reshape(-1), "amax")
        if cache is not None:
            cache[i] = c.first(used[i])
    return stats


def add_visibility_(total: Tensor, more: Tensor) -> Tensor:
    """``total`` [N, 3] with the visibility statistics ``more`` [N, 3] of more pixels (another
    worker's, another view's) taken in, in place: the sums added, the peak the larger."""
    total[:, :VISIBILITY_PEAK] += more[:, :VISIBILITY_PEAK]
    torch.maximum(total[:, VISIBILITY_PEAK], more[:, VISIBILITY_PEAK], out=total[:, VISIBILITY_PEAK])
    return total


def _merged_visibility(parts: list[Tensor | None]) -> Tensor:
    """The workers' visibility statistics as one (:func:`add_visibility_`)."""
    stats = [p for p in parts if p is not None]
    merged = stats[0].clone()
    for p in stats[1:]:
        add_visibility_(merged, p)
    return merged


def _backward_chunks(geom, cache, ids, tile_size, s, grad_out) -> Tensor:
    nf = grad_out.shape[-1] - 1
    dtype = grad_out.dtype
    pix = _pixel_offsets(tile_size, dtype, geom.device)
    fm = _moment_features(tile_size, dtype, geom.device)  # [6, P]
    rows: list[Tensor] = []  # per pair: moments, relative mean, dL/dfeatures
    gids: list[Tensor] = []
    for i in ids:
        c = cache[i]
        if c.gidx.shape[1] == 0:
            continue
        gpix = grad_out.index_select(0, c.tiles)  # [B, P, F+1]
        gf = torch.bmm(gpix, c.f)  # [B, P, K] = dL/dF . f_m
        w, g_power = _backward_kernel(c.g, c.mxr, c.myr, pix, gf, *_thresholds(s))
        dfeat = torch.bmm(gpix.transpose(1, 2).contiguous(), w)  # [B, F+1, K]
        mom = torch.matmul(fm, g_power)  # [B, 6, K]: sums of g_power * (1, x, y, x^2, xy, y^2)
        parts = [mom, torch.stack([c.mxr, c.myr], 1), dfeat[:, :nf]]  # [B, 8 + F, K]
        if s.absgrad:
            parts.append(_absolute_sums(c, fm, g_power))
        row = torch.cat(parts, 1)
        rows.append(row.transpose(1, 2).reshape(-1, row.shape[1]))
        gids.append(c.gidx.reshape(-1))
    if not rows:
        return torch.zeros(geom.shape[0], 6 + nf + 2 * s.absgrad, dtype=dtype, device=geom.device)
    return _pair_gradients(geom, torch.cat(gids), torch.cat(rows))


def _absolute_sums(c: _Chunk, fm: Tensor, g_power: Tensor) -> Tensor:
    """[B, 2, K]: each pair's sums over its tile's pixels of |dL/dmx| and |dL/dmy| of each pixel
    (AbsGS), with dL/dmx = g (a dx + b dy) and dL/dmy = g (b dx + c dy) at that pixel. No moment
    trick here: the absolute value is taken per pixel, so this forms [B, P, K] twice."""
    dx = fm[1][None, :, None] - c.mxr[:, None, :]  # [B, P, K]
    dy = fm[2][None, :, None] - c.myr[:, None, :]
    a, b, cc = (c.g[:, None, :, col] for col in (_A, _B, _C))
    gmx = (a * dx).addcmul_(b, dy).mul_(g_power).abs_().sum(1)
    gmy = (b * dx).addcmul_(cc, dy).mul_(g_power).abs_().sum(1)
    return torch.stack([gmx, gmy], 1)


def _pair_gradients(geom: Tensor, gidx: Tensor, rows: Tensor) -> Tensor:
    """Per-Gaussian gradients [M + 1, 6 + F (+ 2)] (mx, my, a, b, c, o, features, and the
    absolute sums when asked) from per-pair rows [moments of dL/dpower (6), mean relative to the
    tile centre (2), dL/dfeatures (F), the absolute sums (2, :func:`_absolute_sums`)].

    With dx = x - mxr: sum g dx = s1 - mxr s0, sum g dx^2 = s3 - 2 mxr s1 + mxr^2 s0, and so on;
    dpower/dmx = a dx + b dy, dpower/dmy = b dx + c dy, dpower/d(a, b, c) = -(dx^2/2, dx dy, dy^2/2).
    """
    s0, s1, s2, s3, s4, s5, mxr, myr = rows[:, :8].unbind(1)
    g = geom.index_select(0, gidx)
    sdx = s1 - mxr * s0
    sdy = s2 - myr * s0
    sdxx = s3 - 2.0 * mxr * s1 + mxr * mxr * s0
    sdxy = s4 - mxr * s2 - myr * s1 + mxr * myr * s0
    sdyy = s5 - 2.0 * myr * s2 + myr * myr * s0
    ca, cb, cc = g[:, _A], g[:, _B], g[:, _C]
    pair = torch.stack(
        [
            ca * sdx + cb * sdy,
            cb * sdx + cc * sdy,
            -0.5 * sdxx,
            -sdxy,
            -0.5 * sdyy,
            s0 / g[:, _O].clamp_min(1e-30),  # dalpha/do = alpha / o
            *rows[:, 8:].unbind(1),
        ],
        dim=1,
    )
    gbuf = torch.zeros(geom.shape[0], pair.shape[1], dtype=geom.dtype, device=geom.device)
    return gbuf.index_add_(0, gidx, pair)


def thread_budget() -> int:
    """The caller's torch intra-op thread count (as it was before :func:`single_threaded_ops`
    lowered it): the one setting (``torch.set_num_threads``, eg-train's ``--num-threads``) that
    bounds every thread a run uses, the compositor's workers included."""
    with _THREADS_LOCK:
        return _THREADS_STATE["saved"] if _THREADS_STATE["depth"] > 0 else torch.get_num_threads()


def _workers(s: RasterSettings, device: torch.device) -> int:
    """Compositing threads: on the CPU, one per core (each owning single-threaded torch ops); on a
    GPU one, since each chunk is already a few large kernels and threads would only interleave
    their launches."""
    if device.type != "cpu":
        return 1
    return s.workers if s.workers > 0 else thread_budget()


def _chunk_elements(s: RasterSettings, device: torch.device) -> int:
    """Pixel x pair evaluations per chunk: cache-sized on the CPU, large batches on a GPU."""
    return s.chunk_elements if device.type == "cpu" else s.gpu_chunk_elements


class _Composite(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, opacities, feats, support, bins, settings, absgrad_into):  # type: ignore[override]
        dtype = means2d.dtype
        nf = feats.shape[1]
        geom, feat_t = _tables(means2d, conics, opacities, support, feats)
        npix = bins.tile_size**2
        out = torch.zeros(bins.n_tiles, npix, nf + 1, dtype=dtype, device=means2d.device)
        chunks = plan_chunks(bins, _chunk_elements(settings, means2d.device))
        used = [0] * len(chunks)
        # gathered pairs are kept for the backward (O(pairs), not O(pixels x pairs))
        needs_grad = any(ctx.needs_input_grad[:4])
        cache: list[_Chunk | None] | None = [None] * len(chunks) if needs_grad else None
        parts = _run_split(
            lambda _, ids: _forward_chunks(geom, feat_t, bins, chunks, ids, settings, out, used, cache),
            len(chunks), _workers(settings, means2d.device),
        )  # fmt: skip
        # workers keep their own sums (no two threads add into one tensor); the padding row goes
        visibility = _merged_visibility(parts)[:-1] if settings.visibility_stats else out.new_zeros(0, len(VISIBILITY_COLUMNS))
        ctx.mark_non_differentiable(visibility)
        ctx.save_for_backward(geom)
        ctx.cache, ctx.tile_size, ctx.settings = cache, bins.tile_size, settings
        ctx.absgrad_into = (absgrad_into or (means2d, None)) if settings.absgrad else None
        return out, visibility

    @staticmethod
    def backward(ctx, grad_out, grad_visibility):  # type: ignore[override]
        (geom,) = ctx.saved_tensors
        grad_out = grad_out.contiguous()
        parts = _run_split(
            lambda _, ids: _backward_chunks(geom, ctx.cache, ids, ctx.tile_size, ctx.settings, grad_out),
            len(ctx.cache), _workers(ctx.settings, geom.device),
        )  # fmt: skip
        gbuf = parts[0]
        for p in parts[1:]:
            gbuf += p
        gbuf = gbuf[:-1]
        nf = grad_out.shape[-1] - 1
        if ctx.absgrad_into is not None:
            target, rows = ctx.absgrad_into
            sums = gbuf[:, 6 + nf:]
            target.absgrad = sums if rows is None else sums.new_zeros(target.shape).index_copy_(0, rows, sums)
        return gbuf[:, 0:2], gbuf[:, 2:5], gbuf[:, 5], gbuf[:, 6:6 + nf], None, None, None, None


def _tables(
    means2d: Tensor, conics: Tensor, opacities: Tensor, support: Tensor, feats: Tensor
) -> tuple[Tensor, Tensor]:
    """Per-Gaussian geometry [M + 1, 12] and transposed features [F + 1, M + 1] (a last row of
    ones for the alpha). The extra last Gaussian is the padding entry (never drawn)."""
    o = opacities[:, None]
    # Cholesky factor of 0.5 log2(e) [[a, b], [b, c]] (see _chunk_alpha), once per Gaussian
    h = 0.5 * LOG2E
    l11 = torch.sqrt(h * conics[:, :1].clamp_min(1e-30))
    l21 = h * conics[:, 1:2] / l11
    l22sq = (h * conics[:, 2:3] - l21 * l21).clamp_min(0.0)
    geom = torch.cat([means2d, conics, o, torch.log2(o), support, l11, l21, l22sq], -1)
    pad = torch.zeros(1, geom.shape[1], dtype=geom.dtype, device=geom.device)
    pad[0, _LOG2O] = -math.inf
    pad[0, _RX] = pad[0, _RY] = -1.0  # |dx| <= -1 never holds
    pad[0, _A] = pad[0, _C] = pad[0, _L11] = 1.0
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
    absgrad_into: tuple[Tensor, Tensor] | None = None,
) -> Tensor:
    """Composites the binned Gaussians.

    means2d: [M, 2]; conics: [M, 3]; opacities: [M]; feats: [M, F] (colour, depth, ...);
    support: [M, 2] box half-widths (no gradient). Returns [T, tile_size^2, F + 1]: the
    composited features and, last, the accumulated alpha sum_m w_m = 1 - T_final, per tile pixel;
    and, with ``settings.visibility_stats``, [M, 2] per Gaussian: the sum over pixels of its
    weight alpha T and of its alpha (their ratio is the mean transmittance in front of it), else [0, 2].
    With ``settings.absgrad`` the backward leaves the absolute sums [M, 2] (:func:`_absolute_sums`)
    on ``means2d.absgrad``, or, given ``absgrad_into`` = (a tensor [N, 2], the rows [M] of it that
    ``means2d`` holds), on that tensor's, zero on the rows not drawn.
    """
    return _Composite.apply(means2d, conics, opacities, feats, support.detach(), bins, settings, absgrad_into)
