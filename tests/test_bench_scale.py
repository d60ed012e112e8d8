"""The scaling table's ratios and the memory model's byte counts."""

from __future__ import annotations

import pytest

from exploregs_plugin.bench.components.memory import bytes_per_gaussian
from exploregs_plugin.bench.components.scale import table


def test_scale_table_ratios_against_the_first_row():
    rows = [{"ranks": 1, "batch": 1, "seed": s, "steps": 100, "images": 100, "ips": 10.0, "psnr": 20.0 + s,
             "gaussians": 1000} for s in (0, 1)]
    rows += [{"ranks": 2, "batch": 2, "seed": s, "steps": 50, "images": 100, "ips": 16.0, "psnr": 20.1 + s + 0.2 * s,
              "gaussians": 900} for s in (0, 1)]
    lines = table(rows).splitlines()
    assert lines[2].startswith("| 1 | 1 | 100 | 100 | 10.00 | 1.00 | 1.00 |")
    # speedup 1.6, efficiency 0.8 per rank, paired dPSNR mean +0.2 (0.1 and 0.3), spread 0.14
    assert lines[3].startswith("| 2 | 2 | 50 | 100 | 16.00 | 1.60 | 0.80 | 20.70 | +0.20 ± 0.14 | 900 |")


def test_memory_model_counts_parameters_adam_and_statistics(tiny_scene_dir):
    row = bytes_per_gaussian("exploregs-default", "builtin:tiny", sh_degree=3, steps=3)
    assert row["params"] == pytest.approx(59 * 4)  # 3 + 3 + 4 + 1 + 3 + 45 floats
    assert row["grads"] == row["params"]
    assert row["adam"] == pytest.approx(2 * 59 * 4, rel=1e-3)  # two moments (+ a scalar step per tensor)
    assert row["stats"] == pytest.approx(8)  # grad2d and count, float32
    assert row["total"] == pytest.approx(row["params"] * 2 + row["adam"] + row["stats"])
