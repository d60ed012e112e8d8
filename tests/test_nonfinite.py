"""NonFiniteWatch's per-parameter count of non-finite rows (exploregs_plugin/engine/nonfinite.py)."""

from __future__ import annotations

import torch

from exploregs_plugin.engine.nonfinite import nonfinite_count


def test_nonfinite_rows_are_counted_from_row_sums_as_from_every_value():
    """nonfinite_count's row sums (one pass) count exactly the rows holding a NaN or inf, also
    rows of finite values whose float32 sum would overflow."""
    g = torch.Generator().manual_seed(0)
    for shape in [(50, 3), (50, 15, 3), (50,)]:
        p = torch.randn(*shape, generator=g)
        rows = p.reshape(50, -1)
        rows[3, 0] = float("nan")
        rows[7, -1] = float("inf")
        rows[9] = -float("inf")
        rows[11, :] = 3.4e38  # finite: the float32 sum of the row would be inf
        rows[13, 0], rows[13, -1] = float("inf"), -float("inf")  # their sum is NaN
        expected = (~torch.isfinite(p)).reshape(50, -1).any(dim=1).sum() if p.ndim > 1 else (~torch.isfinite(p)).sum()
        assert int(nonfinite_count("shN", p)) == int(expected)
    assert int(nonfinite_count("deformation.grid", torch.tensor([[1.0, float("nan")], [float("inf"), 2.0]]))) == 2


def test_the_compiled_watch_records_the_torch_counts_in_place(monkeypatch):
    """NonFiniteWatch.params on the CPU (one kernel call that tests each value's exponent bits and
    updates the record in place) against the torch path (nonfinite_count per tensor and a
    ``where``): rows with a NaN, +inf or -inf anywhere in them, rows whose float32 sum would
    overflow, float64, a transposed (non-contiguous) tensor, an empty one, a model part's values;
    the same record at 1 and 2 threads, and a later bad step leaves it as it is."""
    import pytest

    from exploregs_plugin.engine import nonfinite
    from exploregs_plugin.kernels import cpp_problem
    from exploregs_plugin.rasterizer.composite import thread_budget

    if cpp_problem() is not None:
        pytest.skip(f"compiled kernels unavailable: {cpp_problem()}")
    g = torch.Generator().manual_seed(1)
    named = [("means", torch.randn(300, 3, generator=g)), ("shN", torch.randn(300, 15, 3, generator=g)),
             ("opacities", torch.randn(300, generator=g)), ("scales", torch.randn(3, 300, generator=g).t()),
             ("quats", torch.randn(300, 4, generator=g, dtype=torch.float64)), ("empty", torch.zeros(0, 3)),
             ("deformation.grid", torch.randn(7, 9, generator=g))]
    values = {name: p for name, p in named}
    rows = torch.randperm(300, generator=g)[:40]
    for k, r in enumerate(rows.tolist()):
        name = ("means", "shN", "opacities", "scales", "quats")[k % 5]
        flat = values[name][r].reshape(-1) if values[name].ndim > 1 else values[name]
        flat[(k * 7) % flat.numel() if values[name].ndim > 1 else r] = (float("nan"), float("inf"), -float("inf"))[k % 3]
    values["means"][rows[0]] = 3.4e38  # finite: its float32 sum would overflow (row may hold a NaN too)
    values["means"][299] = 3.4e38
    values["deformation.grid"][2, 3] = float("nan")
    expected = torch.stack([nonfinite_count(name, p) for name, p in named])
    assert expected.sum() > 20 and int(expected[-1]) == 1
    finite = [(name, torch.zeros_like(p)) for name, p in named]

    def record(compiled: bool) -> torch.Tensor:
        monkeypatch.setattr(nonfinite, "_compiled", lambda tensors, dtypes: compiled)
        watch = nonfinite.NonFiniteWatch()
        watch.params(3, finite, 300)  # nothing recorded
        watch.params(4, named, 300)
        values["opacities"][:] = float("nan")  # a later step: the record keeps step 4
        watch.params(5, named, 301)
        values["opacities"].copy_(opacities)
        return watch._param_record

    opacities = values["opacities"].clone()
    previous = torch.get_num_threads()
    try:
        by_torch = record(False)
        assert by_torch.tolist() == [4, 300, *expected.tolist()]
        for threads in (1, 2):
            torch.set_num_threads(threads)
            assert thread_budget() == threads
            assert torch.equal(record(True), by_torch)
    finally:
        torch.set_num_threads(previous)
