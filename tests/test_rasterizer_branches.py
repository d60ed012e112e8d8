"""Separable position paths, the screen-space gradient, and the per-pixel trace."""

from __future__ import annotations

import torch

from exploregs_plugin.rasterizer import rasterize, rasterize_branched, trace_pixel
from exploregs_plugin.rasterizer.reference import reference_rasterize
from exploregs_plugin.bench.components.raster_scenes import random_scene

F64 = torch.float64


def _scene():
    s = random_scene(40, 32, 28, torch.Generator().manual_seed(11), scale_range=(0.05, 0.25), dtype=F64)
    view = torch.eye(4, dtype=F64)  # a camera that is not at the origin
    view[:3, 3] = torch.tensor([0.1, -0.2, 0.3], dtype=F64)
    s.means = s.means - view[:3, 3]
    s.viewmat = view
    return s


def _weights(s):
    return torch.randn(s.height, s.width, 3, generator=torch.Generator().manual_seed(2), dtype=F64)


def _branch_grads(s):
    """Gradients of a weighted image sum through the 2D-mean, covariance and SH paths."""
    m1, m2, m3 = (s.means.clone().requires_grad_() for _ in range(3))
    img, *_ = rasterize_branched(m1, s.quats, s.scales, s.opacities, s.sh_coeffs, s.camera,
                                 means_cov=m2, means_sh=m3)  # fmt: skip
    (img * _weights(s)).sum().backward()
    return m1.grad, m2.grad, m3.grad


def test_branches_sum_to_total_and_directions():
    s = _scene()
    g_mean, g_cov, g_sh = _branch_grads(s)
    m = s.means.clone().requires_grad_()
    img, _, _, info = rasterize(m, s.quats, s.scales, s.opacities, s.sh_coeffs, s.camera)
    (img * _weights(s)).sum().backward()
    assert torch.allclose(g_mean + g_cov + g_sh, m.grad, rtol=1e-10, atol=1e-12)

    ray = s.means - info["camera_center"]
    ray = ray / ray.norm(dim=-1, keepdim=True)
    live = info["visible"]

    def cos(g):
        return (g * ray).sum(-1) / g.norm(dim=-1).clamp_min(1e-300)

    assert (g_mean[live].norm(dim=-1) > 0).all() and (g_sh[live].norm(dim=-1) > 0).all()
    assert cos(g_mean)[live].abs().max() < 1e-5
    assert cos(g_sh)[live].abs().max() < 1e-5
    assert cos(g_cov)[live].abs().max() > 1e-2  # the covariance path also pulls along the ray
    assert (cos(g_cov)[live].abs() > 1e-3).float().mean() > 0.5


def test_branches_equal_finite_differences_of_reference():
    s = _scene()
    grads = _branch_grads(s)
    w = _weights(s)
    h = 1e-6
    _, _, _, info = rasterize(*s.args())
    ids = torch.nonzero(info["visible"]).squeeze(1)[:3].tolist()
    gen = torch.Generator().manual_seed(5)
    for path, g in zip(("means", "means_cov", "means_sh"), grads):
        for i in ids:
            direction = torch.randn(3, generator=gen, dtype=F64)
            vals = []
            for sign in (1.0, -1.0):
                moved = s.means.clone()
                moved[i] += sign * h * direction
                kw = {"means_cov": s.means, "means_sh": s.means}  # only the path under test moves
                if path == "means":
                    args = (moved,)
                else:
                    args = (s.means,)
                    kw[path] = moved
                img, *_ = reference_rasterize(*args, s.quats, s.scales, s.opacities, s.sh_coeffs, s.camera, **kw)  # fmt: skip
                vals.append((img * w).sum().item())
            fd = (vals[0] - vals[1]) / (2 * h)
            an = (g[i] * direction).sum().item()
            assert abs(fd - an) <= 1e-5 * max(1.0, abs(fd)), (path, i, fd, an)
            assert abs(an) > 1e-6  # every path moves the image


def test_means2d_gradient_is_the_screen_space_gradient():
    s = _scene()
    m = s.means.clone().requires_grad_()
    img, _, _, info = rasterize(m, s.quats, s.scales, s.opacities, s.sh_coeffs, s.camera)
    info["means2d"].retain_grad()
    (img * _weights(s)).sum().backward()
    g2d = info["means2d"].grad
    assert g2d.shape == (40, 2)
    live = info["visible"]
    assert (g2d[~live] == 0).all() and (g2d[live].norm(dim=-1) > 0).any()
    # chain rule through the pinhole projection reproduces the 2D-mean branch of the 3D gradient
    g_mean, _, _ = _branch_grads(s)
    pc = s.means @ s.viewmat[:3, :3].T + s.viewmat[:3, 3]
    fx, fy = s.K[0, 0], s.K[1, 1]
    z = pc[:, 2]
    zero = torch.zeros_like(z)
    jac = torch.stack([fx / z, zero, -fx * pc[:, 0] / z**2, zero, fy / z, -fy * pc[:, 1] / z**2], -1).view(-1, 2, 3)
    g3 = torch.einsum("ni,nij,jk->nk", g2d, jac, s.viewmat[:3, :3])
    assert torch.allclose(g3[live], g_mean[live], rtol=1e-9, atol=1e-12)


def test_trace_pixel_and_dc_dalpha_identity():
    s = _scene()
    bg = torch.tensor([0.3, 0.2, 0.7], dtype=F64)
    img, *_ = rasterize(*s.args(), background=bg)
    grid = [(x, y) for x in range(1, s.width, 4) for y in range(1, s.height, 4)]
    depth_of = {p: len(trace_pixel(*s.args(), *p)["ids"]) for p in grid}
    busiest = sorted(grid, key=lambda p: -depth_of[p])[:4]
    traced = 0
    for x, y in busiest:
        tr = trace_pixel(*s.args(), x, y, background=bg)
        m = len(tr["ids"])
        assert torch.allclose(tr["color"], img[y, x], atol=1e-12)
        assert torch.allclose(tr["T_before"][1:], tr["T_before"][:-1] * (1 - tr["alphas"][:-1]))
        assert (tr["depths"][1:] >= tr["depths"][:-1]).all()
        # dC/dalpha from autograd: alpha = o G, so dC/do = dC/dalpha * alpha / o where unclamped
        for ch in range(3):
            o = s.opacities.clone().requires_grad_()
            im, *_ = rasterize(s.means, s.quats, s.scales, o, s.sh_coeffs, s.camera,
                               background=bg)  # fmt: skip
            im[y, x, ch].backward()
            free = tr["alphas"] < 0.99
            want = tr["dC_dalpha"][:, ch] * tr["alphas"] / s.opacities[tr["ids"]]
            assert torch.allclose(o.grad[tr["ids"]][free], want[free], rtol=1e-9, atol=1e-12)
            others = torch.ones(40, dtype=torch.bool)
            others[tr["ids"]] = False
            assert (o.grad[others] == 0).all()
        traced += m
    assert traced > 10
