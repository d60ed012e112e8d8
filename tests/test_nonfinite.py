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
