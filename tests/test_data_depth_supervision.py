"""The degraded (monocular-like) depth maps of the depth-supervision experiments."""

from __future__ import annotations

import math

import pytest
import torch

from exploregs_plugin.data.depth_supervision import (
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
