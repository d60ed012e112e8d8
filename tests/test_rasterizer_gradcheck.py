"""torch.autograd.gradcheck of the whole rasterizer in float64 on a tiny scene whose every
pixel-Gaussian pair is a stated margin away from each threshold of the image model."""

from __future__ import annotations

import pytest
import torch

from exploregs_plugin.rasterizer import RasterSettings, rasterize
from exploregs_plugin.bench.components.raster_scenes import GaussianScene, random_scene

F64 = torch.float64
# every test runs once with the torch reference and once with the compiled CPU backend
pytestmark = pytest.mark.usefixtures("raster_backend")
S = RasterSettings()
# Margins: gradcheck perturbs by 1e-6, which moves a mean by well under 1e-4 px and an alpha by
# well under 1e-5, so no pair may cross a threshold between the two evaluations.
BOX_MARGIN_PX = 1e-3
ALPHA_MARGIN = 1e-4
T_MARGIN_REL = 1e-3
DEPTH_MARGIN = 1e-2


def _margins(scene: GaussianScene) -> dict[str, float | int]:
    """Distances of all pairs to the thresholds, and counts of pairs on the active side."""
    _, _, _, info = rasterize(*scene.args())
    m2d, con, rad = info["means2d"], info["conics"], info["radii"].to(F64)
    vis = info["visible"]
    ys, xs = torch.meshgrid(torch.arange(scene.height, dtype=F64) + 0.5, torch.arange(scene.width, dtype=F64) + 0.5,
                            indexing="ij")  # fmt: skip
    dx = xs.reshape(-1, 1) - m2d[None, vis, 0]
    dy = ys.reshape(-1, 1) - m2d[None, vis, 1]
    a, b, c = con[vis].unbind(-1)
    raw = scene.opacities[vis] * torch.exp(-0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy)
    box_dist = torch.minimum((dx.abs() - rad[vis, 0]).abs(), (dy.abs() - rad[vis, 1]).abs())
    inside = (dx.abs() <= rad[vis, 0]) & (dy.abs() <= rad[vis, 1])
    alpha = torch.where(inside & (raw >= S.alpha_min), raw.clamp_max(S.alpha_max), torch.zeros_like(raw))
    order = torch.argsort(info["depths"][vis])
    t_after = torch.cumprod(1 - alpha[:, order], 1)
    return {
        "box": box_dist.min().item(),
        "clamp": (raw[inside] - S.alpha_max).abs().min().item(),
        "skip": (raw[inside] - S.alpha_min).abs().min().item(),
        "stop": ((t_after - S.transmittance_min).abs() / S.transmittance_min).min().item(),
        "near": (info["depths"] - 0.01).abs().min().item(),
        "n_clamped": int((inside & (raw > S.alpha_max)).sum()),
        "n_skipped": int((inside & (raw < S.alpha_min) & (raw > 0)).sum()),
        "n_stopped": int((t_after < S.transmittance_min).any(1).sum()),
        "n_box_cut": int((~inside & (raw > S.alpha_min)).sum()),
    }


def _tiny_scene() -> GaussianScene:
    """A stack of four near-opaque Gaussians over one spot (the alpha clamp is active at its
    centre and compositing stops there) plus four random ones, on a 24 x 20 image spanning four
    tiles: the first seed whose pairs all keep the margins."""
    for seed in range(100):
        g = torch.Generator().manual_seed(seed)
        s = random_scene(8, 24, 20, g, scale_range=(0.05, 0.3), sh_degree=1, focal=30.0, dtype=F64)
        rnd = torch.rand(4, 4, generator=g, dtype=F64)
        z = torch.tensor([2.0, 2.5, 3.0, 3.5], dtype=F64) + 0.2 * rnd[0]
        u, v = 10.0 + 4.0 * rnd[1], 8.0 + 4.0 * rnd[2]
        s.means[:4] = torch.stack([(u - 12.0) / 30.0 * z, (v - 10.0) / 30.0 * z, z], -1)
        s.scales[:4] = (3.0 / 30.0 * z * (1.0 + 0.3 * rnd[3]))[:, None] * torch.tensor([1.0, 0.8, 1.2], dtype=F64)
        s.opacities[:4] = torch.tensor([0.996, 0.95, 0.95, 0.9], dtype=F64)
        m = _margins(s)
        if (m["box"] > BOX_MARGIN_PX and m["clamp"] > ALPHA_MARGIN and m["skip"] > ALPHA_MARGIN * 0.01
                and m["stop"] > T_MARGIN_REL and m["near"] > DEPTH_MARGIN and m["n_clamped"] and m["n_skipped"]
                and m["n_stopped"] and m["n_box_cut"]):  # fmt: skip
            return s
    raise AssertionError("no seed gives a scene with all margins")


def test_gradcheck_float64_all_parameters():
    s = _tiny_scene()
    bg = torch.tensor([0.3, 0.6, 0.1], dtype=F64)

    def f(means, quats, scales, opacities, sh):
        img, alpha, depth, _ = rasterize(means, quats, scales, opacities, sh, s.camera,
                                         background=bg)  # fmt: skip
        return torch.cat([img, alpha, depth], -1)

    inputs = tuple(t.clone().requires_grad_() for t in (s.means, s.quats, s.scales, s.opacities, s.sh_coeffs))
    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-5, rtol=1e-4, fast_mode=True)
    # exhaustive (every input, every output) for the means on pixels around the stack
    sub = (inputs[0],)
    assert torch.autograd.gradcheck(lambda m: f(m, *inputs[1:])[5:15:2, 7:17:2], sub, eps=1e-6, atol=1e-5, rtol=1e-4)
