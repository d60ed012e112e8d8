"""The sharing benchmark on a tiny run: each format's size and error, the smaller splats' rows."""

import pytest

from exploregs_plugin.bench.components.share import attribution_rows, count_rows, format_rows, tables
from exploregs_plugin.runs import load_run


@pytest.fixture()
def run_dir(tiny_run_dir):
    return tiny_run_dir


def test_format_rows_measure_each_file(run_dir, tmp_path):
    run = load_run(run_dir, "cpu")
    n, degree = run.pipeline.model.num_gaussians, run.pipeline.model.config.sh_degree
    rows = {r["format"]: r for r in format_rows(run, tmp_path)}
    assert set(rows) == {"ply", "splat", "spz", "compressed-ply", "spz sh bits 8 8"}
    assert all(r["gaussians"] == n for r in rows.values())
    # float32 PLY: xyz, normals, opacity, scales, rotation (14) and 3 (degree + 1)^2 SH per Gaussian,
    # plus a header of under 2 kB; its render differs by one float32 rounding of the frame map
    per_gaussian = 4 * (14 + 3 * (degree + 1) ** 2)
    assert per_gaussian < rows["ply"]["bytes_per_gaussian"] < per_gaussian + 2000 / n
    assert rows["ply"]["worst_view_psnr_to_float"] > 80.0
    assert rows["splat"]["bytes_per_gaussian"] == 32.0 and rows["splat"]["sh_degree"] == 0
    for name in ("spz", "compressed-ply", "spz sh bits 8 8"):
        assert rows[name]["bytes"] < rows["ply"]["bytes"] and 25.0 < rows[name]["worst_view_psnr_to_float"] < 80.0


def test_count_rows_shrink_the_splat(run_dir, tmp_path):
    rows = count_rows(run_dir, [1, 4], 10, tmp_path)
    assert [(r["fraction"], r["finetune_steps"]) for r in rows] == [(1, 0), (4, 0), (4, 10)]
    full, quarter = rows[0], rows[1]
    assert full["weight_kept"] == 1.0 and quarter["gaussians"] == full["gaussians"] // 4
    assert 0.25 < quarter["weight_kept"] < 1.0 and quarter["ply_bytes"] < full["ply_bytes"] / 3
    assert "| x1/4 | 10 |" in tables([], rows)
    assert all(r["lpips"] is None or r["lpips"] > 0 for r in rows)


def test_attribution_quantises_one_value_at_a_time(run_dir, tmp_path):
    run = load_run(run_dir, "cpu")
    rows = attribution_rows(run, tmp_path)
    assert [r["quantised"] for r in rows] == ["means", "scales", "quats", "opacities", "sh0", "shN"]
    # a PLY keeps every value up to one float32 rounding of the frame map: every row scores as the run
    exact = attribution_rows(run, tmp_path, fmt="ply")
    from exploregs_plugin.evaluation.metrics import evaluate
    psnr = evaluate(run.pipeline.model, run.pipeline.datamanager)["psnr"]
    assert all(abs(r["test_psnr"] - psnr) < 1e-3 for r in exact)
    assert "| shN |" in tables([], [], rows)
