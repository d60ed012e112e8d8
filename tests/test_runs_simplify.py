"""A smaller splat: significance = total compositing weight over the training views, the N of
largest weight x peak kept (with their Adam moments), optional fine-tuning without densification."""

import math

import pytest
import torch

from exploregs_plugin.cameras import Camera
from exploregs_plugin.model.gaussians import render_params, rgb_to_sh0
from exploregs_plugin.rasterizer import RasterSettings
from exploregs_plugin.runs import load_run
from exploregs_plugin.model.significance import (CUT_COLUMNS, add_view_, cut_order, most_significant,
                                                visibility_cut_order, visibility_totals)
from exploregs_plugin.runs.simplify import simplify


def _weights(params, cameras, settings, background=None):
    """Each Gaussian's summed compositing weight alpha T over ``cameras`` (its significance)."""
    return visibility_totals(params, cameras, settings, background)[:, 0]


def _camera(width=48, height=40, focal=50.0) -> Camera:
    K = torch.tensor([[focal, 0.0, width / 2], [0.0, focal, height / 2], [0.0, 0.0, 1.0]])
    return Camera(viewmat=torch.eye(4), K=K, width=width, height=height, name="front")


def _scene(depths, log_sigmas, opacity_logits, offsets=None) -> dict[str, torch.Tensor]:
    n = len(depths)
    offsets = offsets or [(0.0, 0.0)] * n
    means = torch.tensor([[x, y, z] for (x, y), z in zip(offsets, depths)], dtype=torch.float32)
    return {
        "means": means,
        "scales": torch.tensor(log_sigmas, dtype=torch.float32)[:, None].repeat(1, 3),
        "quats": torch.tensor([[1.0, 0.0, 0.0, 0.0]] * n),
        "opacities": torch.tensor(opacity_logits, dtype=torch.float32),
        "sh0": rgb_to_sh0(torch.full((n, 3), 0.5)).reshape(n, 1, 3),
        "shN": torch.zeros(n, 0, 3),
    }


def test_the_weights_of_a_view_add_up_to_its_accumulated_alpha():
    # sum_j alpha_j T_j at a pixel is the pixel's accumulated alpha, so over the view the weights
    # total the alpha image's sum
    params = _scene([2.0, 3.0, 4.0, 2.5], [-1.5, -1.0, -1.2, -2.0], [0.0, 2.0, 1.0, -1.0],
                    [(0.0, 0.0), (0.2, 0.1), (-0.3, 0.0), (0.1, -0.2)])
    camera = _camera()
    weights = _weights(params, [camera], RasterSettings())
    _, alpha, _, _ = render_params(params, camera, 0, None, RasterSettings())
    assert weights.dtype == torch.float64 and weights.shape == (4,)
    assert (weights > 0).all()
    assert math.isclose(float(weights.sum()), float(alpha.double().sum()), rel_tol=1e-4)
    # two views: the sums add
    twice = _weights(params, [camera, camera], RasterSettings())
    torch.testing.assert_close(twice, 2 * weights)


def test_the_peak_is_the_largest_weight_at_one_pixel_over_the_views():
    params = _scene([3.0, 2.0], [-1.5, -2.5], [0.0, 9.0], [(0.0, 0.0), (0.3, 0.2)])
    near, far = _camera(), _camera(focal=25.0)
    one, other = (visibility_totals(params, [c], RasterSettings()) for c in (near, far))
    both = visibility_totals(params, [near, far], RasterSettings())
    assert both.shape == (2, 4)
    torch.testing.assert_close(both[:, :2], one[:, :2] + other[:, :2])  # the sums add over the views
    torch.testing.assert_close(both[:, 2], torch.maximum(one[:, 2], other[:, 2]))  # the peak is the larger
    # the view weight: the summed weight of the view that draws the row most
    torch.testing.assert_close(one[:, 3], one[:, 0])
    torch.testing.assert_close(both[:, 3], torch.maximum(one[:, 0], other[:, 0]))
    # the opaque one in front paints the pixel at its centre almost alone; the other's peak is about its
    # opacity, 0.5, at its own centre (the opaque one, 7 pixels away, covers little of it)
    assert 0.9 < float(both[1, 2]) <= RasterSettings().alpha_max
    assert 0.45 < float(both[0, 2]) <= 0.5


def test_the_cut_keeps_a_small_opaque_gaussian_over_a_wide_faint_one_that_paints_more():
    # texture is small Gaussians that paint their few pixels alone; a wide faint one spreads a little
    # weight over many pixels: its summed weight is larger, but removing it costs each pixel little
    params = _scene([3.0, 3.0], [-0.8, -3.5], [-3.5, 6.0], [(0.0, 0.0), (0.3, 0.2)])
    totals = visibility_totals(params, [_camera()], RasterSettings())
    weight, peak = totals[:, 0], totals[:, 2]
    assert weight[0] > 2 * weight[1] and peak[1] > 10 * peak[0]
    assert most_significant(weight, 1).tolist() == [True, False]  # the weight alone keeps the faint one
    assert most_significant(visibility_cut_order(totals), 1).tolist() == [False, True]


def test_the_cut_keeps_a_gaussian_one_view_needs_over_one_that_paints_as_little_in_each_of_many():
    # row 0: the side of an object that one photo of a 360-degree capture sees, weight 4 there; row
    # 1: weight 1 in each of six photos. Summed over the views row 1 paints more (6 against 4), but
    # removing it costs each photo little; removing row 0 costs its photo four times as much
    views = [torch.tensor([[4.0, 4.0, 0.5], [1.0, 1.0, 0.5]], dtype=torch.float64)]
    views += [torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 0.5]], dtype=torch.float64)] * 5
    totals = torch.zeros(2, len(CUT_COLUMNS), dtype=torch.float64)
    for view in views:
        add_view_(totals, view)
    assert totals.tolist() == [[4.0, 4.0, 0.5, 4.0], [6.0, 6.0, 0.5, 1.0]]
    assert most_significant(cut_order(totals[:, 0], totals[:, 2]), 1).tolist() == [False, True]  # summed: row 1
    assert most_significant(visibility_cut_order(totals), 1).tolist() == [True, False]


def test_a_gaussian_hidden_behind_an_opaque_one_is_not_significant():
    # the hidden one is larger and as opaque as the front one: opacity x volume x pixels covered
    # would rank it first; what it paints is (1 - alpha_front) of its footprint, nearly nothing
    # (front: 18 px wide on screen, back: 5 px, so the front covers the back's whole footprint)
    params = _scene([2.0, 8.0], [-0.3, -0.2], [9.0, 9.0])
    weights = _weights(params, [_camera(128, 128)], RasterSettings())
    volume_proxy = torch.sigmoid(params["opacities"]) * params["scales"].exp().prod(dim=1)
    assert volume_proxy[1] > volume_proxy[0]
    assert weights[1] < 0.05 * weights[0]
    assert most_significant(weights, 1).tolist() == [True, False]


def test_most_significant_keeps_count_rows_and_breaks_ties_by_index():
    values = torch.tensor([1.0, 3.0, 3.0, 0.0, 2.0], dtype=torch.float64)
    assert most_significant(values, 2).tolist() == [False, True, True, False, False]
    assert most_significant(values, 3).tolist() == [False, True, True, False, True]
    ties = torch.tensor([1.0, 1.0, 1.0, 1.0], dtype=torch.float64)
    assert most_significant(ties, 2).tolist() == [True, True, False, False]
    assert most_significant(values, 99).all()
    with pytest.raises(ValueError, match="max-gaussians must be >= 1"):
        most_significant(values, 0)


@pytest.fixture()
def run_dir(tiny_run_dir):
    return tiny_run_dir


def _train_psnr(run) -> float:
    model, dm = run.pipeline.model, run.pipeline.datamanager
    total = 0.0
    for index, camera in enumerate(dm.train_cameras):
        _, target, _ = dm.train_item(index)
        with torch.no_grad():
            image = model.render(camera, model.config.sh_degree, dm.background)[0].clamp(0, 1)
        total += float(((image - target) ** 2).mean())
    return -10.0 * math.log10(total / len(dm.train_cameras))


def test_pruning_keeps_the_rows_and_their_adam_moments(run_dir):
    run = load_run(run_dir, "cpu")
    params = run.pipeline.params
    n = int(params["means"].shape[0])
    full_psnr = _train_psnr(run)
    totals = visibility_totals({k: v.detach() for k, v in params.items()}, run.pipeline.datamanager.train_cameras,
                               run.pipeline.model.config.raster, run.pipeline.background)
    significance = totals[:, 0]
    keep = most_significant(visibility_cut_order(totals), n // 2)
    assert not torch.equal(keep, most_significant(significance, n // 2))  # the peak changes the choice here
    expected_means = params["means"].detach()[keep].clone()
    expected_moment = run.pipeline.optimizers["means"].state[params["means"]]["exp_avg"][keep].clone()
    result = simplify(run.pipeline, run.step, n // 2)
    assert (result.before, result.after, result.finetune_steps) == (n, n // 2, 0)
    assert torch.equal(params["means"].detach(), expected_means)  # same rows, same order
    assert torch.equal(run.pipeline.optimizers["means"].state[params["means"]]["exp_avg"], expected_moment)
    kept_share = float(significance[keep].sum() / significance.sum())
    assert result.kept_weight_share == pytest.approx(kept_share) and 0.5 < kept_share <= 1.0
    # half the Gaussians carrying most of the weight: the images lose little
    assert _train_psnr(run) > full_psnr - 3.0


def test_finetuning_recovers_and_is_deterministic(run_dir):
    runs = [load_run(run_dir, "cpu") for _ in range(3)]
    n = int(runs[0].pipeline.params["means"].shape[0])
    count = max(n // 8, 1)
    plain = simplify(runs[0].pipeline, runs[0].step, count)
    tuned = [simplify(run.pipeline, run.step, count, finetune_steps=30) for run in runs[1:]]
    assert plain.after == tuned[0].after == count and tuned[0].finetune_steps == 30
    assert _train_psnr(runs[1]) > _train_psnr(runs[0])
    assert int(runs[1].pipeline.params["means"].shape[0]) == count  # no densification while tuning
    for name, value in runs[1].pipeline.params.items():
        assert torch.equal(value, runs[2].pipeline.params[name]), name


def test_eg_export_writes_the_smaller_splat_and_a_web_page(run_dir, tmp_path, capsys):
    from exploregs_plugin.io.scene_files import read_scene
    from exploregs_plugin.scripts import export as export_script
    from exploregs_plugin.viewer.web_page import read_recording

    n = load_run(run_dir, "cpu").pipeline.model.num_gaussians
    result = export_script.main(export_script.ExportArgs(run_dir, out=tmp_path / "small.spz", max_gaussians=n // 4,
                                                         finetune_steps=5, device="cpu"))
    assert result.written == n // 4 and result.format == "spz"
    assert read_scene(result.path).num_gaussians == n // 4
    out = capsys.readouterr().out
    assert f"kept {n // 4} of {n} Gaussians (" in out and "fine-tuned 5 steps" in out

    page = export_script.main(export_script.ExportArgs(run_dir, out=tmp_path / "web", format="web",
                                                       max_gaussians=n // 2, device="cpu"))
    assert page.num_gaussians == n // 2 and page.index.is_file()
    payload, buffers = read_recording(page.recording.read_bytes())
    splats = [m for _, m in payload["messages"] if m["type"] == "GaussianSplatsMessage"]
    assert len(splats) == 1 and buffers[splats[0]["props"]["buffer"]["__binary_index"]].nbytes == 32 * (n // 2)
    assert "python3 -m http.server" in capsys.readouterr().out

    with pytest.raises(ValueError, match="give --max-gaussians too"):
        export_script.main(export_script.ExportArgs(run_dir, out=tmp_path / "x.ply", finetune_steps=5, device="cpu"))
