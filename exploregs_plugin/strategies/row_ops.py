"""Every change to the set of Gaussians goes through this module.

One helper, :func:`update_params_and_optimizers`, applies a row function to every named
parameter and a matching function to every per-row tensor of its Adam state (``exp_avg``,
``exp_avg_sq``), so the moments can never drift from their rows. Each op also applies the same
row change to the strategy's per-Gaussian statistics (``stats``: a dict of tensors whose first
dimension is the Gaussian count, e.g. accumulated screen-space gradients).

Conventions shared by all ops:
- ``params``: ``torch.nn.ParameterDict`` (or dict) of raw parameters with N rows each;
  ``optimizers``: one Adam per trainable key, a single param group holding that parameter.
- Rows that keep their identity keep their moments and statistics; new rows (copies, children,
  appended or relocated rows) start with zero moments. Statistics of copies and children are
  inherited from the parent (as in gsplat), appended rows get zero statistics.
- The Adam ``step`` counter is per parameter, not per row, and is left unchanged.
- Masks are ``[N]`` bool; all randomness comes from an explicit ``torch.Generator``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Mapping, MutableMapping

import torch
from torch import Tensor

from ..kernels.rows import gather_rows
from ..rasterizer.projection import quats_to_rotmats
from .relocation import relocation_update

Params = MutableMapping[str, torch.nn.Parameter]
Optimizers = Mapping[str, torch.optim.Optimizer]
Stats = MutableMapping[str, Tensor]


def num_gaussians(params: Mapping[str, Tensor]) -> int:
    """Row count N of the Gaussian parameters (0 for an empty dict)."""
    for p in params.values():
        return int(p.shape[0])
    return 0


@torch.no_grad()
def update_params_and_optimizers(
    param_fn: Callable[[str, Tensor], Tensor],
    optimizer_fn: Callable[[str, Tensor], Tensor],
    params: Params,
    optimizers: Optimizers,
    names: Iterable[str] | None = None,
) -> None:
    """Replace each named parameter by ``param_fn(name, p)`` and remap its optimizer state.

    ``optimizer_fn(state_key, value)`` is applied to every per-row tensor of the Adam state
    (everything but the scalar ``step``); the state is re-keyed to the new parameter object and
    the optimizer's param group is pointed at it, so the next ``optimizer.step()`` updates the
    new rows with the remapped moments.
    """
    for name in list(params.keys()) if names is None else list(names):
        old = params[name]
        # no detach: under no_grad param_fn's result records nothing (each operator is a dispatch)
        new = torch.nn.Parameter(param_fn(name, old), requires_grad=old.requires_grad)
        params[name] = new
        optimizer = optimizers.get(name)
        if optimizer is None:
            if old.requires_grad:
                raise ValueError(
                    f"parameter '{name}' is trainable but has no optimizer; the optimizers "
                    f"must hold one Adam per trainable parameter (keys: {sorted(optimizers)})"
                )
            continue
        for group in optimizer.param_groups:
            if not any(p is old for p in group["params"]):
                continue
            group["params"] = [new if p is old else p for p in group["params"]]
            state = optimizer.state.pop(old, None)
            if state is None:
                continue  # optimizer has not stepped yet: no moments to carry
            for key, value in state.items():
                if _is_row_state(key, value):
                    state[key] = optimizer_fn(key, value)
            optimizer.state[new] = state


def _is_row_state(key: str, value: object) -> bool:
    """Whether an optimizer state entry has a row per Gaussian (Adam's moments; not ``step``)."""
    return key != "step" and isinstance(value, Tensor) and value.dim() > 0


def _update_stats(stats: Stats, fn: Callable[[Tensor], Tensor]) -> None:
    for key, value in list(stats.items()):
        if isinstance(value, Tensor):
            stats[key] = fn(value)


def _zeros_rows(v: Tensor, n: int) -> Tensor:
    return v.new_zeros((n, *v.shape[1:]))


def _check_mask(mask: Tensor, n: int, op: str) -> Tensor:
    if mask.dtype != torch.bool or mask.shape != (n,):
        raise ValueError(
            f"ops.{op}: mask must be a bool tensor of shape [{n}], got "
            f"{mask.dtype} {tuple(mask.shape)}"
        )
    return mask


def _masked_rows(mask: Tensor, count: int | None = None) -> tuple[Tensor, Tensor]:
    """(selected, rest): the indices of the True and of the False entries of ``mask`` [N], each
    ascending. Without ``count`` two nonzeros, each of which reads its size from the device; with
    ``count`` (how many entries are True, when the caller knows it) none: a stable sort puts the
    False entries first, in order, then the True ones, the same indices."""
    if count is None:
        return torch.where(mask)[0], torch.where(~mask)[0]
    order = torch.argsort(mask.to(torch.uint8), stable=True)
    return order[mask.shape[0] - count:], order[:mask.shape[0] - count]


@torch.no_grad()
def duplicate(params: Params, optimizers: Optimizers, stats: Stats, mask: Tensor) -> int:
    """Append a copy of every masked Gaussian at the end (3DGS clone). Returns the count."""
    sel = torch.where(_check_mask(mask, num_gaussians(params), "duplicate"))[0]
    if len(sel) == 0:
        return 0
    update_params_and_optimizers(
        lambda name, p: torch.cat([p, p[sel]]),
        lambda key, v: torch.cat([v, _zeros_rows(v, len(sel))]),
        params,
        optimizers,
    )
    _update_stats(stats, lambda v: torch.cat([v, v[sel]]))
    return len(sel)


@torch.no_grad()
def split(
    params: Params,
    optimizers: Optimizers,
    stats: Stats,
    mask: Tensor,
    generator: torch.Generator,
    scale_factor: float = 1.6,
    count: int | None = None,
) -> int:
    """Replace every masked Gaussian by two children sampled from its own Gaussian.

    Child means are mu + R diag(s) z with z ~ N(0, I) (two draws per parent), child scales are
    s / ``scale_factor`` (3DGS: 1.6), every other attribute is copied. Parents are removed;
    unselected rows keep their order and come first, then all first children, then all second
    children. Returns the number of parents split. ``count``: how many entries of ``mask`` are
    True, when the caller knows it (then nothing is read from the device to find the rows).
    """
    if scale_factor <= 0:
        raise ValueError(f"ops.split: scale_factor must be positive, got {scale_factor}")
    sel, rest = _masked_rows(_check_mask(mask, num_gaussians(params), "split"), count)
    if len(sel) == 0:
        return 0
    means, log_scales = params["means"], params["scales"]
    scales = torch.exp(log_scales[sel])  # under no_grad: nothing to detach
    rot = quats_to_rotmats(params["quats"][sel], few_operators=True)  # [S, 3, 3], few rows
    z = torch.randn(2, len(sel), 3, generator=generator, dtype=means.dtype, device=generator.device)
    if z.device != means.device:
        z = z.to(means.device)
    offsets = torch.einsum("nij,nj,bnj->bni", rot, scales, z).reshape(-1, 3)  # [2 S, 3]: first children, then second
    log_factor = math.log(scale_factor)
    # Every tensor is one gather of the rows in their new order (the rest, then each parent twice),
    # and the children are changed in place: p[sel] + offset and p[sel] - log(factor) are the same
    # floats however they are reached, with a few operators per tensor instead of four.
    order = torch.cat([rest, sel, sel])
    children = slice(len(rest), None)
    # the parameters, their Adam moments (the children's start at zero) and the statistics gathered
    # at once: on the CPU one compiled call instead of a gather per tensor and a slice per moment
    moments = [v for name, p in params.items() if name in optimizers
               for key, v in optimizers[name].state.get(p, {}).items()
               if _is_row_state(key, v)]
    kept_stats = [v for v in stats.values() if isinstance(v, Tensor)]
    sources = [*params.values(), *moments, *kept_stats]
    zero_from = [None] * len(params) + [len(rest)] * len(moments) + [None] * len(kept_stats)
    gathered = {id(t): rows for t, rows in zip(sources, gather_rows(sources, order, zero_from))}

    def param_fn(name: str, p: Tensor) -> Tensor:
        rows = gathered[id(p)]
        if name == "means":
            rows[children].add_(offsets)
        elif name == "scales":
            rows[children].sub_(log_factor)
        return rows

    update_params_and_optimizers(param_fn, lambda key, v: gathered[id(v)], params, optimizers)
    _update_stats(stats, lambda v: gathered[id(v)])
    return len(sel)


@torch.no_grad()
def remove(params: Params, optimizers: Optimizers, stats: Stats, mask: Tensor) -> int:
    """Delete every masked Gaussian. Returns the count removed."""
    keep = torch.where(~_check_mask(mask, num_gaussians(params), "remove"))[0]
    n_removed = int(mask.sum())
    if n_removed == 0:
        return 0
    update_params_and_optimizers(lambda name, p: p[keep], lambda key, v: v[keep], params, optimizers)
    _update_stats(stats, lambda v: v[keep])
    return n_removed


@torch.no_grad()
def append(
    params: Params, optimizers: Optimizers, stats: Stats, rows: Mapping[str, Tensor]
) -> int:
    """Append new Gaussians given as raw rows for every parameter key. Returns the count.

    rows: {key: [M, ...]} with the same keys and trailing shapes as ``params``. New rows get
    zero moments and zero statistics.
    """
    missing = set(params.keys()) - set(rows.keys())
    extra = set(rows.keys()) - set(params.keys())
    if missing or extra:
        raise ValueError(
            f"ops.append: rows must have exactly the parameter keys; missing {sorted(missing)}, "
            f"unexpected {sorted(extra)}"
        )
    counts = {int(r.shape[0]) for r in rows.values()}
    if len(counts) != 1:
        raise ValueError(f"ops.append: rows disagree on their count: {sorted(counts)}")
    m = counts.pop()
    for key, r in rows.items():
        if tuple(r.shape[1:]) != tuple(params[key].shape[1:]):
            raise ValueError(
                f"ops.append: rows['{key}'] has trailing shape {tuple(r.shape[1:])}, the "
                f"parameter has {tuple(params[key].shape[1:])}"
            )
    if m == 0:
        return 0
    update_params_and_optimizers(
        lambda name, p: torch.cat([p, rows[name].to(device=p.device, dtype=p.dtype)]),
        lambda key, v: torch.cat([v, _zeros_rows(v, m)]),
        params,
        optimizers,
    )
    _update_stats(stats, lambda v: torch.cat([v, _zeros_rows(v, m)]))
    return m


@torch.no_grad()
def reset_opacity(params: Params, optimizers: Optimizers, value: float) -> None:
    """Clamp every opacity to at most ``value`` (3DGS: 0.01) and zero the opacity moments."""
    if not 0.0 < value < 1.0:
        raise ValueError(f"ops.reset_opacity: value must be in (0, 1), got {value}")
    ceiling = math.log(value / (1.0 - value))  # logit(value)
    update_params_and_optimizers(
        lambda name, p: p.clamp(max=ceiling),
        lambda key, v: torch.zeros_like(v),
        params,
        optimizers,
        names=["opacities"],
    )


def _shared_relocation(
    params: Params, sampled: Tensor, binoms: Tensor, min_opacity: float
) -> tuple[Tensor, Tensor]:
    """Raw (logit opacity, log scale) for sources shared by their copies (MCMC eq. 9)."""
    opacities = torch.sigmoid(params["opacities"].detach()[sampled])
    scales = torch.exp(params["scales"].detach()[sampled])
    # A source drawn c times is now shared by c + 1 Gaussians (itself and c copies).
    ratios = torch.bincount(sampled)[sampled] + 1
    new_o, new_s = relocation_update(opacities, scales, ratios, binoms)
    eps = torch.finfo(new_o.dtype).eps
    new_o = new_o.clamp(min=min_opacity, max=1.0 - eps)
    return torch.logit(new_o), torch.log(new_s.clamp_min(torch.finfo(new_s.dtype).tiny))


def _with_sources_updated(name: str, p: Tensor, sampled: Tensor, new_logit: Tensor, new_log_scale: Tensor) -> Tensor:
    """A copy of parameter ``name`` with the sampled sources' opacity/scale replaced."""
    p = p.clone()
    if name == "opacities":
        p[sampled] = new_logit.to(p.dtype)
    elif name == "scales":
        p[sampled] = new_log_scale.to(p.dtype)
    return p


@torch.no_grad()
def relocate(
    params: Params,
    optimizers: Optimizers,
    stats: Stats,
    dead_mask: Tensor,
    generator: torch.Generator,
    binoms: Tensor,
    min_opacity: float = 0.005,
) -> int:
    """Move every dead Gaussian onto a live one drawn in proportion to opacity (3DGS-MCMC).

    Sources and their copies get the relocation update; the dead rows take the sources'
    updated attributes. Moments and statistics of sources and relocated rows are zeroed (both
    are new Gaussians now). Nothing happens when no Gaussian is dead or none is alive.
    Returns the number relocated.
    """
    n = num_gaussians(params)
    _check_mask(dead_mask, n, "relocate")
    dead = torch.where(dead_mask)[0]
    alive = torch.where(~dead_mask)[0]
    if len(dead) == 0 or len(alive) == 0:
        return 0
    weights = torch.sigmoid(params["opacities"].detach()[alive]).flatten()
    if not torch.isfinite(weights).all() or float(weights.sum()) <= 0.0:
        return 0
    sampled = alive[torch.multinomial(weights, len(dead), replacement=True, generator=generator)]
    new_logit, new_log_scale = _shared_relocation(params, sampled, binoms, min_opacity)
    touched = torch.cat([sampled, dead])

    def param_fn(name: str, p: Tensor) -> Tensor:
        p = _with_sources_updated(name, p, sampled, new_logit, new_log_scale)
        p[dead] = p[sampled]
        return p

    def zero_touched(v: Tensor) -> Tensor:
        v = v.clone()
        v[touched] = 0
        return v

    update_params_and_optimizers(param_fn, lambda key, v: zero_touched(v), params, optimizers)
    _update_stats(stats, zero_touched)
    return len(dead)


@torch.no_grad()
def sample_add(
    params: Params,
    optimizers: Optimizers,
    stats: Stats,
    n: int,
    generator: torch.Generator,
    binoms: Tensor,
    min_opacity: float = 0.005,
) -> int:
    """Append ``n`` copies of Gaussians drawn in proportion to opacity (3DGS-MCMC growth).

    Sources get the relocation update and the copies take it too; sources' moments are kept
    (as gsplat does), copies start at zero moments and zero statistics. Returns the count.
    """
    if n < 0:
        raise ValueError(f"ops.sample_add: n must be >= 0, got {n}")
    if n == 0 or num_gaussians(params) == 0:
        return 0
    weights = torch.sigmoid(params["opacities"].detach()).flatten()
    if not torch.isfinite(weights).all() or float(weights.sum()) <= 0.0:
        return 0
    sampled = torch.multinomial(weights, n, replacement=True, generator=generator)
    new_logit, new_log_scale = _shared_relocation(params, sampled, binoms, min_opacity)

    def param_fn(name: str, p: Tensor) -> Tensor:
        p = _with_sources_updated(name, p, sampled, new_logit, new_log_scale)
        return torch.cat([p, p[sampled]])

    update_params_and_optimizers(
        param_fn, lambda key, v: torch.cat([v, _zeros_rows(v, n)]), params, optimizers
    )
    _update_stats(stats, lambda v: torch.cat([v, _zeros_rows(v, n)]))
    return n
