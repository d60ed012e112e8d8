"""Near-side diagnostics on constructed cases: who sees a point, the region and hidden-ness of a
Gaussian, the error split by visibility, and the statistics pooled over views."""

from __future__ import annotations

import csv
import json
import math

import torch

from exploregs_plugin.analysis.blending import composited_pairs
from exploregs_plugin.analysis.branches import ViewProblem
from exploregs_plugin.analysis.nearside import (
    NO_REGION, ViewStats, accumulate, class_summary, error_by_visibility, gaussian_regions, hidden_from,
    gradient_cancellation, project_pixels, reference_psnrs, seen_by, unproject, view_stats, visibility_histogram,
)
from exploregs_plugin.analysis.nearside_report import occluded_parts
from exploregs_plugin.cameras import Camera
from exploregs_plugin.model.gaussians import SH_C0
from exploregs_plugin.scripts.analyze import Nearside, main, parse

F64 = torch.float64
W, H = 8, 6
K = torch.tensor([[8.0, 0.0, W / 2], [0.0, 8.0, H / 2], [0.0, 0.0, 1.0]], dtype=F64)


def _viewmat(x: float) -> torch.Tensor:
    """A camera at (x, 0, 0) looking down +z (identity rotation)."""
    m = torch.eye(4, dtype=F64)
    m[0, 3] = -x
    return m


def _three_views():
    """Three cameras above a plane at depth 5; in views 1 and 2 an occluder at depth 2 covers the
    whole image, so the plane is seen only by view 0."""
    viewmats = torch.stack([_viewmat(0.0), _viewmat(0.1), _viewmat(-0.1)])
    Ks = K.expand(3, 3, 3).clone()
    depths = torch.full((3, H, W), 5.0, dtype=F64)
    depths[1:] = 2.0
    return viewmats, Ks, depths


def test_unproject_lands_on_the_pixel_centres_it_came_from():
    depth = torch.linspace(2.0, 6.0, H * W, dtype=F64).reshape(H, W)
    vm = _viewmat(0.3)
    points = unproject(depth, K, vm).reshape(-1, 3)
    z, col, row, inside = project_pixels(points, vm[None], K[None], H, W)
    assert bool(inside.all())
    assert torch.allclose(z[0], depth.reshape(-1))
    assert col[0].tolist() == [i % W for i in range(H * W)]
    assert row[0].tolist() == [i // W for i in range(H * W)]


def test_a_point_behind_an_occluder_is_seen_by_one_view_and_hidden_from_two():
    viewmats, Ks, depths = _three_views()
    point = torch.tensor([[0.0, 0.0, 5.0]], dtype=F64)
    assert seen_by(point, viewmats, Ks, depths)[:, 0].tolist() == [True, False, False]
    assert hidden_from(point, viewmats, Ks, depths)[:, 0].tolist() == [False, True, True]
    # a point outside every image is neither seen nor hidden
    far_left = torch.tensor([[-100.0, 0.0, 5.0]], dtype=F64)
    assert seen_by(far_left, viewmats, Ks, depths).sum() == 0 and hidden_from(far_left, viewmats, Ks, depths).sum() == 0
    assert visibility_histogram(torch.tensor([0, 1, 1, 2, 7]), (0, 1, 3)) == [1, 3, 1]


def test_gaussian_regions_take_the_label_where_they_lie_on_the_surface():
    viewmats, Ks, depths = _three_views()
    labels = torch.zeros(3, H, W, dtype=torch.long)
    labels[0] = 2  # the plane is 'occluded' in view 0
    means = torch.tensor([[0.0, 0.0, 5.0],    # on the plane, behind the occluder in views 1, 2
                          [0.0, 0.0, 1.0],    # in front of everything, on no surface
                          [0.0, 0.0, 2.0]], dtype=F64)  # on the occluder of views 1 and 2
    reg = gaussian_regions(means, viewmats, Ks, depths, labels, n_labels=3)
    assert reg.region.tolist() == [2, NO_REGION, 0]
    assert reg.front_views.tolist() == [1, 3, 3]
    assert reg.inside_views.tolist() == [3, 3, 3]
    assert reg.on_surface.tolist() == [1, 0, 2]
    assert reg.hidden().tolist() == [True, False, False]


def test_error_by_visibility_splits_the_squared_error_and_gives_the_ceilings():
    sq = torch.tensor([0.01, 0.01, 0.04, 0.0], dtype=F64)
    counts = torch.tensor([0, 3, 3, 9])
    rows = error_by_visibility(sq, counts, (0, 1, 5))
    assert [r["pixels"] for r in rows] == [1, 2, 1]
    assert math.isclose(rows[0]["share_sq_error"], 0.01 / 0.06)
    assert math.isclose(rows[1]["psnr"], 10 * math.log10(1 / 0.025))
    assert rows[0]["region_psnr_if_fitted_from_here"] == math.inf  # every pixel fitted
    # pixels seen by >= 1 view fitted: only the unseen pixel's 0.01 remains, over 4 pixels
    assert math.isclose(rows[1]["region_psnr_if_fitted_from_here"], 10 * math.log10(4 / 0.01))
    assert rows[2]["psnr"] == math.inf and rows[2]["views_hi"] == -1


def test_pooled_statistic_compensated_and_lit_means():
    # Gaussian 0: |g| 3e-4 at T 1 and 1e-4 at T 0.1; Gaussian 1: visible in both, composited only in view 0
    v0 = ViewStats(torch.tensor([3e-4, 1e-4]), torch.tensor([True, True]), torch.tensor([2.0, 0.5]),
                   torch.tensor([2.0, 1.0]))
    v1 = ViewStats(torch.tensor([1e-4, 0.0]), torch.tensor([True, True]), torch.tensor([0.1, 0.0]),
                   torch.tensor([1.0, 0.0]))
    acc = accumulate([v0, v1], t_floor=0.05)
    assert torch.allclose(acc.statistic, torch.tensor([2e-4, 0.5e-4], dtype=F64))
    assert torch.allclose(acc.compensated, torch.tensor([(3e-4 + 1e-3) / 2, 1e-4 / 0.5 / 2], dtype=F64))
    assert torch.allclose(acc.statistic_lit, torch.tensor([2e-4, 1e-4], dtype=F64))
    assert torch.allclose(acc.tbar, torch.tensor([2.1 / 3.0, 0.5], dtype=F64))
    rows = class_summary(torch.tensor([0, 2]), acc, 1.5e-4, torch.zeros(2, 3), {0: "other", 2: "occluded"})
    assert [r["frac_above"] for r in rows] == [1.0, 0.0]
    assert [r["frac_above_compensated"] for r in rows] == [1.0, 0.0]
    assert math.isclose(rows[0]["share_statistic"], 0.8, rel_tol=1e-6)
    assert rows[1]["mean_lit_views"] == 1.0 and rows[1]["mean_visible_views"] == 2.0


def test_view_stats_transmittance_matches_the_composited_pairs():
    # two coincident Gaussians on the optical axis, the front one at opacity 0.6
    w, h = 16, 12
    K2 = torch.tensor([[16.0, 0.0, w / 2], [0.0, 16.0, h / 2], [0.0, 0.0, 1.0]])
    depths = [2.0, 3.0]
    means = torch.tensor([[0.0, 0.0, z] for z in depths])
    scales = torch.tensor([[3.0 * z / 16.0] * 3 for z in depths])
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]] * 2)
    rgb = torch.tensor([[0.9, 0.2, 0.1], [0.1, 0.5, 0.8]])
    params = {"means": means, "quats": quats, "scales": torch.log(scales),
              "opacities": torch.logit(torch.tensor([0.6, 0.7])), "sh0": ((rgb - 0.5) / SH_C0)[:, None, :],
              "shN": torch.zeros(2, 0, 3)}
    camera = Camera(torch.eye(4), K2, w, h, "two")
    view = ViewProblem(params, camera, torch.zeros(h, w, 3), 0, lambda a, b: (a - b).abs().mean())
    stats = view_stats(view)
    pairs = composited_pairs(params, camera)
    for g in range(2):
        sel = pairs["ids"] == g
        expected = float((pairs["alphas"][sel] * pairs["T_before"][sel]).sum() / pairs["alphas"][sel].sum())
        assert math.isclose(float(stats.weight[g] / stats.alpha[g]), expected, rel_tol=1e-4)
    assert math.isclose(float(stats.weight[0] / stats.alpha[0]), 1.0, rel_tol=1e-6)
    assert float(stats.weight[1] / stats.alpha[1]) < 0.7
    assert bool(stats.visible.all()) and bool((stats.grad > 0).all())


def test_reference_predictors_on_a_one_pixel_checkerboard():
    yy, xx = torch.meshgrid(torch.arange(5), torch.arange(5), indexing="ij")
    image = ((xx + yy) % 2).to(F64)[..., None].expand(5, 5, 3)
    mask = torch.zeros(5, 5, dtype=torch.bool)
    mask[1:4, 1:4] = True  # away from the replicated edges
    ref = reference_psnrs(image[None], mask[None], blurs=(1, 3))
    assert ref["blur_1"] == math.inf  # no blur: the truth itself
    assert math.isclose(ref["blur_3"], 10 * math.log10(81 / 16))  # every 3x3 box is off by 4/9
    assert math.isclose(ref["shift_1px"], 0.0, abs_tol=1e-12)  # every pixel takes its opposite
    # 5 ones and 4 zeros inside the mask: mean 5/9, MSE = (5 (4/9)^2 + 4 (5/9)^2) / 9 = 20/81
    assert math.isclose(ref["region_mean"], 10 * math.log10(81 / 20))


def test_occluded_parts_split_hidden_from_out_of_view():
    labels = torch.tensor([[2, 2, 0]])
    seen = torch.tensor([[1, 4, 1]])
    hidden = torch.tensor([[20, 0, 20]])
    parts = occluded_parts(labels, seen, hidden)
    assert parts["occluded"].tolist() == [[True, True, False]]
    assert parts["occluded-hidden"].tolist() == [[True, False, False]]
    assert parts["occluded-out-of-view"].tolist() == [[False, True, False]]


def test_gradient_cancellation_of_opposite_pixel_parts():
    # Gaussian 0: two pixels pulling opposite ways (cancel); Gaussian 1: two agreeing; Gaussian 2: none
    ids = torch.tensor([0, 0, 1, 1])
    grad_px = torch.tensor([[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, 1.0]], dtype=F64)
    c = gradient_cancellation(ids, grad_px, 3, width=4, height=2)  # NDC: x * 2, y * 1
    assert c["net"].tolist() == [0.0, 2.0, 0.0]
    assert c["absolute"].tolist() == [4.0, 2.0, 0.0]
    assert c["ratio"][:2].tolist() == [0.0, 1.0] and math.isnan(float(c["ratio"][2]))
    assert c["pixels"].tolist() == [2, 2, 0]


def test_the_command_on_a_tiny_run_agrees_with_the_run_s_own_evaluation(tmp_path, tiny_scene_dir):
    main(parse(["grad-branches", "--data", "builtin:tiny", "--max-steps", "20", "--every", "20", "--views", "1",
                "--out", str(tmp_path / "train")]))
    run = tmp_path / "train" / "run"
    args = parse(["nearside", "--run", str(run), "--cancellation-views", "0", "--device", "cpu",
                  "--out", str(tmp_path / "ns")])
    assert isinstance(args, Nearside)
    result = main(args)
    out = tmp_path / "ns"
    assert (out / "nearside.png").read_bytes()[:4] == b"\x89PNG"
    refs = {(r["split"], r["part"]): r for r in csv.DictReader(open(out / "nearside_references.csv"))}
    whole, hidden, oov = (refs[("test", p)] for p in ("occluded", "occluded-hidden", "occluded-out-of-view"))
    assert int(hidden["pixels"]) + int(oov["pixels"]) == int(whole["pixels"])
    # the occluded region's PSNR is the one the run's evaluation reported (same checkpoint, same pooling)
    metrics = json.loads((run / "metrics.json").read_text())
    assert math.isclose(float(whole["model"]), metrics["region_psnr"]["occluded"], abs_tol=1e-3)
    pooled = [r for r in result["pixels"] if r["split"] == "test" and r["part"] == "occluded" and r["view"] == "all"]
    assert math.isclose(sum(r["share_pixels"] for r in pooled), 1.0)
    assert sum(r["pixels"] for r in pooled) == int(whole["pixels"])
    classes = {r["region"] for r in result["gaussians"]}
    assert {"other", "occluded-hidden", "off-surface"} <= classes
    assert sum(r["gaussians"] for r in result["gaussians"]) == metrics["num_gaussians"]
    assert {r["view"] for r in result["cancellation"]} == {result["cancellation"][0]["view"]}
