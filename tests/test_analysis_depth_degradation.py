"""The degraded (monocular-like) depth maps of the depth-supervision experiments."""

from __future__ import annotations

import math

import pytest
import torch

from exploregs_plugin.analysis.depth_degradation import (
    N_WAVES, DepthSupervisionConfig, degrade_depth, smooth_field,
)


def test_degraded_depth_statistics_and_determinism():
    h, w = 96, 128
    depth = torch.full((h, w, 1), 4.0)
    depth[0, 0, 0] = 0.0  # invalid pixels stay as they are
    depth[1, 0, 0] = float("inf")
    noise_only = degrade_depth(depth, 3, DepthSupervisionConfig(noise_std=0.05, seed=1))
    rel = noise_only[2:] / 4.0 - 1.0
    assert rel.std().item() == pytest.approx(0.05, rel=0.1) and abs(rel.mean().item()) < 0.005
    assert noise_only[0, 0, 0] == 0.0 and math.isinf(noise_only[1, 0, 0].item())
    bias_only = degrade_depth(depth, 3, DepthSupervisionConfig(bias_amplitude=0.1, seed=1))
    brel = bias_only[2:, :, 0] / 4.0 - 1.0
    # smooth: a pixel step changes the bias by at most b N k / sqrt(N / 2) (N waves, k = 2 pi / wavelength)
    bound = 0.1 * N_WAVES * (2 * math.pi / (0.5 * w)) / math.sqrt(N_WAVES / 2)
    assert (brel[:, 1:] - brel[:, :-1]).abs().max() <= bound and brel.abs().max() > 0.05
    again = degrade_depth(depth, 3, DepthSupervisionConfig(bias_amplitude=0.1, seed=1))
    other_view = degrade_depth(depth, 4, DepthSupervisionConfig(bias_amplitude=0.1, seed=1))
    assert torch.equal(again, bias_only) and not torch.equal(other_view, bias_only)
    assert (degrade_depth(depth, 0, DepthSupervisionConfig(noise_std=5.0))[2:] > 0).all()
    plain = DepthSupervisionConfig()
    assert not plain.active and plain.apply(depth, 0) is depth


def test_smooth_field_has_unit_rms_and_bad_configs_fail():
    field = smooth_field(256, 256, 64.0, torch.Generator().manual_seed(0))
    assert field.pow(2).mean().sqrt().item() == pytest.approx(1.0, rel=0.35)
    with pytest.raises(ValueError, match="noise_std"):
        DepthSupervisionConfig(noise_std=-1.0)
    with pytest.raises(ValueError, match="bias_wavelength"):
        DepthSupervisionConfig(bias_wavelength=0.0)
    with pytest.raises(ValueError, match=r"\[H, W, 1\]"):
        degrade_depth(torch.ones(4, 4), 0, DepthSupervisionConfig(noise_std=0.1))


def test_non_finite_depth_is_masked_as_no_depth_and_counted(tiny_scene_dir, tmp_path):
    """Sky stored as inf (and holes as NaN) mean "no depth here": masked, counted in one warning."""
    import shutil

    import numpy as np

    from exploregs_plugin.data import DataManagerConfig
    from exploregs_plugin.model.losses import depth_l1

    root = shutil.copytree(tiny_scene_dir, tmp_path / "scene")
    path = root / "depths" / "0001.npy"
    depth = np.load(path)
    depth[:5, :] = np.inf  # the top rows are sky
    depth[10, 10] = np.nan
    np.save(path, depth)
    n_masked = 5 * depth.shape[1] + 1
    n_maps = len(list((root / "depths").glob("*.npy")))
    with pytest.warns(UserWarning, match=rf"depths: {n_masked} of {n_maps * depth.size} depth pixels .* in 1 of "
                                         rf"{n_maps} depth maps are not finite .* masked as no depth \(e\.g\. 0001\.npy\)"):
        dm = DataManagerConfig(data=str(root), test_every=0, use_dataset_split=False,
                               cache_dir=str(tmp_path / "cache")).setup()
    index = [c.name for c in dm.train_cameras].index("0001.png")
    loaded = dm.train_item(index)[2]["depth"]
    assert torch.isfinite(loaded).all() and (loaded[:5] == 0).all() and loaded[10, 10, 0] == 0
    assert torch.equal(loaded[5:10], torch.from_numpy(depth[5:10] * dm.parsed.depth_scale).float()[..., None])
    # the loss sees no depth there: a render that only differs on masked pixels costs nothing
    render = loaded.clone()
    render[:5] = 123.0
    assert depth_l1(render, loaded).item() == 0.0


def test_mono_depth_pipeline_degrades_the_map_the_depth_term_reads():
    from exploregs_plugin.analysis.depth_degradation import DegradedDepthTerm, MonoDepthPipelineConfig
    from exploregs_plugin.engine.loss_terms import DepthTerm, PhotometricTerm, ViewLossInput
    from exploregs_plugin.method_configs import get_method

    config = get_method("exploregs-mono-depth").config.pipeline
    assert isinstance(config, MonoDepthPipelineConfig) and config.depth_loss_weight > 0
    terms = config.loss_terms()
    assert type(terms[0]) is PhotometricTerm and type(terms[1]) is DegradedDepthTerm
    assert MonoDepthPipelineConfig(depth_loss_weight=0.0).loss_terms() == [PhotometricTerm(0.2)]
    g = torch.Generator().manual_seed(0)
    truth = 2.0 + torch.rand(8, 6, 1, generator=g)
    view = ViewLossInput(image=torch.zeros(8, 6, 3), target=torch.zeros(8, 6, 3), depth=truth.clone(),
                         extras={"depth": truth}, index=5)
    plain, _ = DepthTerm(1.0)(view)
    degraded, parts = terms[1](view)
    assert float(plain) == 0.0  # the render equals the true map: no loss without degradation
    expected = (degrade_depth(truth, 5, config.depth_supervision) - truth).abs().mean()
    assert float(parts["depth"]) == pytest.approx(float(expected), rel=1e-5) and float(degraded) > 0
