"""strategies.row_ops: parameters, Adam moments and statistics stay aligned with the rows."""

from __future__ import annotations

import math

import pytest
import torch

from exploregs_plugin.strategies import row_ops
from exploregs_plugin.strategies.relocation import binomial_table
from exploregs_plugin.strategies.synthetic import adam_steps, make_gaussians, make_optimizers

N = 12


def _setup(n: int = N, sh_degree: int = 1, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    params = make_gaussians(n, g, sh_degree=sh_degree)
    optimizers = make_optimizers(params)
    adam_steps(params, optimizers, g, steps=2)
    stats = {"grad2d": torch.arange(n, dtype=torch.float32) + 1.0, "count": torch.arange(n, dtype=torch.float32) * 2}
    return g, params, optimizers, stats


def _snapshot(params, optimizers, stats):
    snap = {}
    for name, p in params.items():
        st = optimizers[name].state[p]
        snap[name] = {
            "param": p.detach().clone(),
            "exp_avg": st["exp_avg"].clone(),
            "exp_avg_sq": st["exp_avg_sq"].clone(),
            "step": st["step"].clone(),
        }
    snap["_stats"] = {k: v.clone() for k, v in stats.items()}
    return snap


def _check_rows(params, optimizers, stats, snap, new_idx, old_idx, skip_param=()):
    """Rows new_idx carry old rows old_idx: parameters (unless skipped), moments and stats."""
    for name, p in params.items():
        st = optimizers[name].state[p]
        assert optimizers[name].param_groups[0]["params"][0] is p
        assert st["exp_avg"].shape == p.shape and st["exp_avg_sq"].shape == p.shape
        assert torch.equal(st["step"], snap[name]["step"])
        if name not in skip_param:
            assert torch.equal(p.detach()[new_idx], snap[name]["param"][old_idx]), name
        assert torch.equal(st["exp_avg"][new_idx], snap[name]["exp_avg"][old_idx]), name
        assert torch.equal(st["exp_avg_sq"][new_idx], snap[name]["exp_avg_sq"][old_idx]), name
    for key, value in stats.items():
        assert value.shape[0] == params["means"].shape[0]


def _check_zero_moments(params, optimizers, rows):
    for name, p in params.items():
        st = optimizers[name].state[p]
        assert torch.count_nonzero(st["exp_avg"][rows]) == 0
        assert torch.count_nonzero(st["exp_avg_sq"][rows]) == 0


def _mask(n, idx):
    m = torch.zeros(n, dtype=torch.bool)
    m[list(idx)] = True
    return m


def test_duplicate_aligns_rows_and_zeroes_new_moments():
    g, params, optimizers, stats = _setup()
    snap = _snapshot(params, optimizers, stats)
    sel = [1, 4, 7]
    assert row_ops.duplicate(params, optimizers, stats, _mask(N, sel)) == 3
    assert params["means"].shape[0] == N + 3
    _check_rows(params, optimizers, stats, snap, torch.arange(N), torch.arange(N))
    new = torch.arange(N, N + 3)
    for name, p in params.items():
        assert torch.equal(p.detach()[new], snap[name]["param"][sel])
    _check_zero_moments(params, optimizers, new)
    assert torch.equal(stats["grad2d"], torch.cat([snap["_stats"]["grad2d"], snap["_stats"]["grad2d"][sel]]))


def test_remove_aligns_rows():
    g, params, optimizers, stats = _setup()
    snap = _snapshot(params, optimizers, stats)
    gone = [0, 5, 6, 11]
    keep = torch.tensor([i for i in range(N) if i not in gone])
    assert row_ops.remove(params, optimizers, stats, _mask(N, gone)) == 4
    assert params["quats"].shape[0] == N - 4
    _check_rows(params, optimizers, stats, snap, torch.arange(N - 4), keep)
    assert torch.equal(stats["count"], snap["_stats"]["count"][keep])


def test_remove_everything_leaves_empty_consistent_state():
    g, params, optimizers, stats = _setup()
    row_ops.remove(params, optimizers, stats, torch.ones(N, dtype=torch.bool))
    for name, p in params.items():
        assert p.shape[0] == 0
        assert optimizers[name].state[p]["exp_avg"].shape == p.shape
    assert stats["grad2d"].shape == (0,)


def test_split_children_from_parent_and_alignment():
    g, params, optimizers, stats = _setup()
    snap = _snapshot(params, optimizers, stats)
    sel = [2, 3, 9]
    rest = torch.tensor([i for i in range(N) if i not in sel])
    assert row_ops.split(params, optimizers, stats, _mask(N, sel), torch.Generator().manual_seed(3)) == 3
    assert params["means"].shape[0] == N - 3 + 6
    _check_rows(params, optimizers, stats, snap, torch.arange(len(rest)), rest)
    children = torch.arange(len(rest), len(rest) + 6)
    parents = torch.tensor(sel + sel)
    _check_zero_moments(params, optimizers, children)
    for name in ("quats", "opacities", "sh0", "shN"):
        assert torch.equal(params[name].detach()[children], snap[name]["param"][parents])
    expected_scales = snap["scales"]["param"][parents] - math.log(1.6)
    assert torch.allclose(params["scales"].detach()[children], expected_scales, atol=1e-6)
    assert torch.equal(stats["grad2d"][children], snap["_stats"]["grad2d"][parents])
    # Children are parent mean + R diag(s) z: mapped back to the parent's frame, the offsets are
    # standard-normal draws of a sensible size (|z| < 6), not arbitrary jumps.
    from exploregs_plugin.rasterizer.projection import quats_to_rotmats

    rot = quats_to_rotmats(snap["quats"]["param"][parents])
    offset = params["means"].detach()[children] - snap["means"]["param"][parents]
    z = torch.einsum("nji,nj->ni", rot, offset) / torch.exp(snap["scales"]["param"][parents])
    assert z.abs().max() < 6.0 and z.abs().max() > 1e-3
    # The two children of one parent are distinct draws.
    assert not torch.allclose(offset[:3], offset[3:])


def test_append_new_rows_zero_moments_and_stats():
    g, params, optimizers, stats = _setup(sh_degree=0)
    snap = _snapshot(params, optimizers, stats)
    new = make_gaussians(5, torch.Generator().manual_seed(9), sh_degree=0)
    rows = {k: v.detach() for k, v in new.items()}
    assert row_ops.append(params, optimizers, stats, rows) == 5
    _check_rows(params, optimizers, stats, snap, torch.arange(N), torch.arange(N))
    tail = torch.arange(N, N + 5)
    for name, p in params.items():
        assert torch.equal(p.detach()[tail], rows[name])
    _check_zero_moments(params, optimizers, tail)
    assert torch.count_nonzero(stats["grad2d"][tail]) == 0
    assert params["shN"].shape == (N + 5, 0, 3)


def test_append_rejects_missing_keys_and_bad_shapes():
    g, params, optimizers, stats = _setup()
    rows = {k: v.detach()[:2] for k, v in params.items()}
    bad = dict(rows)
    del bad["sh0"]
    with pytest.raises(ValueError, match="missing"):
        row_ops.append(params, optimizers, stats, bad)
    bad = dict(rows, means=torch.zeros(2, 4))
    with pytest.raises(ValueError, match="trailing shape"):
        row_ops.append(params, optimizers, stats, bad)


def test_mask_validation():
    g, params, optimizers, stats = _setup()
    with pytest.raises(ValueError, match="bool tensor of shape"):
        row_ops.remove(params, optimizers, stats, torch.ones(N - 1, dtype=torch.bool))


def test_reset_opacity_clamps_and_zeroes_only_opacity_moments():
    g, params, optimizers, stats = _setup()
    snap = _snapshot(params, optimizers, stats)
    row_ops.reset_opacity(params, optimizers, 0.01)
    o = torch.sigmoid(params["opacities"].detach())
    assert torch.all(o <= 0.01 + 1e-7)
    lower = torch.sigmoid(snap["opacities"]["param"]) < 0.01
    assert torch.equal(params["opacities"].detach()[lower], snap["opacities"]["param"][lower])
    _check_zero_moments({"opacities": params["opacities"]}, optimizers, torch.arange(N))
    for name in ("means", "scales", "quats", "sh0", "shN"):
        assert torch.equal(optimizers[name].state[params[name]]["exp_avg"], snap[name]["exp_avg"])


def test_relocate_reuses_dead_rows_and_zeroes_their_moments():
    g, params, optimizers, stats = _setup()
    with torch.no_grad():
        params["opacities"][[0, 4, 8]] = -10.0  # dead: sigmoid < 0.005
    snap = _snapshot(params, optimizers, stats)
    dead = torch.sigmoid(params["opacities"].detach()) <= 0.005
    n = row_ops.relocate(params, optimizers, stats, dead, torch.Generator().manual_seed(1), binomial_table())
    assert n == 3 and params["means"].shape[0] == N
    o = torch.sigmoid(params["opacities"].detach())
    assert torch.all(o[[0, 4, 8]] > 0.005)
    # Each dead row now equals some live row exactly (a relocated copy shares its source).
    for d in (0, 4, 8):
        same = torch.all(params["means"].detach() == params["means"].detach()[d], dim=-1)
        same[d] = False
        assert same.any()
        assert torch.count_nonzero(optimizers["means"].state[params["means"]]["exp_avg"][d]) == 0
        assert stats["grad2d"][d] == 0
    untouched = [i for i in range(N) if torch.count_nonzero(optimizers["means"].state[params["means"]]["exp_avg"][i]) > 0]
    assert len(untouched) >= N - 6
    for i in untouched:
        assert torch.equal(params["means"].detach()[i], snap["means"]["param"][i])


def test_sample_add_appends_copies():
    g, params, optimizers, stats = _setup()
    n = row_ops.sample_add(params, optimizers, stats, 4, torch.Generator().manual_seed(2), binomial_table())
    assert n == 4 and params["means"].shape[0] == N + 4
    tail = torch.arange(N, N + 4)
    _check_zero_moments(params, optimizers, tail)
    for i in tail:
        same = torch.all(params["means"].detach()[:N] == params["means"].detach()[i], dim=-1)
        assert same.sum() == 1  # a copy of exactly one source
        src = torch.where(same)[0][0]
        assert torch.equal(params["scales"].detach()[src], params["scales"].detach()[i])


@pytest.mark.parametrize("op", ["duplicate", "split", "remove", "append", "relocate", "sample_add"])
def test_adam_step_after_op_equals_rebuilt_optimizer(op):
    """Stepping the surgically updated Adam equals stepping a fresh Adam loaded with the
    surviving rows' saved moments (zeros for new rows)."""
    g, params, optimizers, stats = _setup()
    with torch.no_grad():
        params["opacities"][[1, 6]] = -9.0
    saved = _snapshot(params, optimizers, stats)
    # Tag rows so their origin can be recovered after the op: row i has means[:, 0] == tag[i].
    with torch.no_grad():
        params["means"][:, 0] = torch.arange(N, dtype=torch.float32) * 1000.0
    saved["means"]["param"] = params["means"].detach().clone()
    mask = _mask(N, [1, 6, 10])
    gen = torch.Generator().manual_seed(5)
    if op == "duplicate":
        row_ops.duplicate(params, optimizers, stats, mask)
    elif op == "split":
        row_ops.split(params, optimizers, stats, mask, gen)
    elif op == "remove":
        row_ops.remove(params, optimizers, stats, mask)
    elif op == "append":
        row_ops.append(params, optimizers, stats, {k: v.detach()[:3] * 0 + 7.0 for k, v in params.items()})
    elif op == "relocate":
        row_ops.relocate(params, optimizers, stats, torch.sigmoid(params["opacities"].detach()) <= 0.005, gen, binomial_table())
    else:
        row_ops.sample_add(params, optimizers, stats, 3, gen, binomial_table())
    n_new = params["means"].shape[0]
    # Which new rows are survivors that kept their identity (and moments)?
    survivor_src = {}
    moments = optimizers["means"].state[params["means"]]["exp_avg"]
    for i in range(n_new):
        tag = params["means"].detach()[i, 0]
        src = int(torch.round(tag / 1000.0))
        if 0 <= src < N and torch.isclose(tag, torch.tensor(src * 1000.0)) and torch.count_nonzero(moments[i]) > 0:
            survivor_src[i] = src
    assert len(survivor_src) >= N - 6

    grads = {name: torch.randn(p.shape, generator=g) for name, p in params.items()}
    for name, p in params.items():
        rebuilt_p = torch.nn.Parameter(p.detach().clone())
        rebuilt = torch.optim.Adam([rebuilt_p], lr=1e-3, eps=1e-15)
        exp_avg = torch.zeros_like(p)
        exp_avg_sq = torch.zeros_like(p)
        for i, src in survivor_src.items():
            exp_avg[i] = saved[name]["exp_avg"][src]
            exp_avg_sq[i] = saved[name]["exp_avg_sq"][src]
        rebuilt.state[rebuilt_p] = {"step": saved[name]["step"].clone(), "exp_avg": exp_avg, "exp_avg_sq": exp_avg_sq}
        p.grad = grads[name].clone()
        rebuilt_p.grad = grads[name].clone()
        optimizers[name].step()
        rebuilt.step()
        assert torch.equal(p.detach(), rebuilt_p.detach()), (op, name)


def test_the_compiled_gather_of_many_tensors_equals_index_select_and_zeroes_the_tail(monkeypatch):
    """kernels.rows.gather_rows (on the CPU one compiled call copying rows as bytes) against the
    torch path (index_select per tensor, the tails zeroed): float32, float64, int32 and bool
    tensors of one to three dimensions, a repeated index, a tail zeroed from its start, in the
    middle and past the end; an index out of range is refused."""
    import pytest

    from exploregs_plugin.kernels import cpp_problem, rows

    if cpp_problem() is not None:
        pytest.skip(f"compiled kernels unavailable: {cpp_problem()}")
    g = torch.Generator().manual_seed(3)
    tensors = [torch.randn(9, 3, generator=g), torch.randn(9, 5, 3, generator=g, dtype=torch.float64),
               torch.randint(-5, 5, (9,), generator=g, dtype=torch.int32), torch.rand(9, 2, generator=g) > 0.5,
               -torch.zeros(9, 4)]
    order = torch.tensor([8, 0, 3, 3, 1, 7, 7])
    zero_from = [None, 0, 4, None, 7]
    compiled = rows.gather_rows(tensors, order, zero_from)
    monkeypatch.setattr(rows, "cpp_problem", lambda: "forced torch path")
    by_torch = rows.gather_rows(tensors, order, zero_from)
    for a, b in zip(compiled, by_torch):
        assert a.dtype == b.dtype and a.shape == b.shape and a.view(-1).numpy().tobytes() == b.view(-1).numpy().tobytes()
    assert not compiled[1].any() and not compiled[2][4:].any() and compiled[2][:4].equal(tensors[2][[8, 0, 3, 3]])
    assert torch.signbit(compiled[4]).all()  # the rows copied as bytes: -0.0 stays -0.0
    monkeypatch.setattr(rows, "cpp_problem", lambda: None)
    with pytest.raises(RuntimeError, match="out of range"):
        rows.gather_rows(tensors, torch.tensor([0, 9]), [None] * len(tensors))
