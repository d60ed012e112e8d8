"""Projection and SH colours against gsplat's pure-torch implementation (a numerical peer)."""

from __future__ import annotations

import pytest
import torch

pytest.importorskip("gsplat", reason="gsplat is not installed (optional numerical peer)")
_impl = pytest.importorskip("gsplat.cuda._torch_impl", reason="gsplat has no pure-torch reference module")

from exploregs_plugin.rasterizer import RasterSettings  # noqa: E402
from exploregs_plugin.rasterizer.projection import covariances_3d, project_gaussians  # noqa: E402
from exploregs_plugin.bench.components.raster_scenes import random_scene  # noqa: E402
from exploregs_plugin.rasterizer.sh import eval_sh  # noqa: E402

F64 = torch.float64


def _posed_scene(seed: int, width: int, height: int):
    s = random_scene(300, width, height, torch.Generator().manual_seed(seed), scale_range=(0.005, 0.5), dtype=F64)
    # a general pose and a non-centred principal point; some Gaussians outside the guard band
    ang = torch.tensor(0.3, dtype=F64)
    rot = torch.tensor([[torch.cos(ang), 0, torch.sin(ang)], [0, 1, 0], [-torch.sin(ang), 0, torch.cos(ang)]],
                       dtype=F64)  # fmt: skip
    view = torch.eye(4, dtype=F64)
    view[:3, :3] = rot
    view[:3, 3] = torch.tensor([0.2, -0.1, 0.5], dtype=F64)
    s.viewmat = view
    s.K[0, 2], s.K[1, 2] = 0.3 * width, 0.6 * height
    s.means = (s.means - view[:3, 3]) @ rot  # world points whose camera coordinates are the sampled ones
    s.means[:20, 0] += 3.0
    return s


@pytest.mark.parametrize("antialiased", [False, True])
def test_projection_matches_gsplat(antialiased):
    s = _posed_scene(0, 64, 40)
    settings = RasterSettings(antialiased=antialiased)
    proj = project_gaussians(s.means, s.quats, s.scales, s.opacities, s.viewmat, s.K, s.width, s.height, 0.01, 1e10,
                             settings)  # fmt: skip
    covars = covariances_3d(s.quats, s.scales)
    gs_covars, _ = _impl._quat_scale_to_covar_preci(s.quats, s.scales, compute_covar=True, compute_preci=False)
    assert torch.allclose(covars, gs_covars, rtol=1e-10, atol=1e-14)
    radii, means2d, depths, conics, comp = _impl._fully_fused_projection(
        s.means, gs_covars, s.viewmat[None], s.K[None], s.width, s.height, eps2d=0.3, calc_compensations=antialiased
    )
    vis = proj.visible
    assert vis.sum() > 200
    assert torch.allclose(proj.means2d[vis], means2d[0, vis], rtol=1e-10, atol=1e-9)
    assert torch.allclose(proj.conics[vis], conics[0, vis], rtol=1e-9, atol=1e-12)
    assert torch.allclose(proj.depths, depths[0], rtol=1e-12)
    if antialiased:
        assert torch.allclose(proj.opacities[vis], s.opacities[vis] * comp[0, vis], rtol=1e-9)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_sh_matches_gsplat(degree):
    g = torch.Generator().manual_seed(degree)
    dirs = torch.randn(500, 3, generator=g, dtype=F64)
    coeffs = torch.randn(500, 16, 3, generator=g, dtype=F64)
    unit = dirs / dirs.norm(dim=-1, keepdim=True)
    ours = eval_sh(coeffs, unit, degree)
    theirs = _impl._spherical_harmonics(degree, dirs, coeffs)
    assert torch.allclose(ours, theirs, rtol=1e-10, atol=1e-12)
