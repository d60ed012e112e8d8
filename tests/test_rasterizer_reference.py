"""The fast rasterizer against the dense float64 reference: outputs and every gradient,
on random scenes and on the nasty inputs real scenes produce."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch

from exploregs_plugin.cameras import Camera
from exploregs_plugin.rasterizer import RasterSettings, rasterize
from exploregs_plugin.rasterizer.reference import reference_rasterize
from exploregs_plugin.bench.components.raster_scenes import GaussianScene, random_scene

F64 = torch.float64
# every test runs once with the torch reference and once with the compiled CPU backend
pytestmark = pytest.mark.usefixtures("raster_backend")


def _run(fn, scene: GaussianScene, dtype, **kw):
    """Renders, backpropagates a fixed random weighting of all outputs; returns outputs and grads."""
    params = [t.detach().to(dtype).clone().requires_grad_() for t in
              (scene.means, scene.quats, scene.scales, scene.opacities, scene.sh_coeffs)]  # fmt: skip
    extra = {k: (v.to(dtype) if isinstance(v, torch.Tensor) else v) for k, v in kw.items()}
    out = fn(*params, scene.camera.to(dtype), **extra)
    gen = torch.Generator().manual_seed(7)
    wts = torch.randn(scene.height, scene.width, 5, generator=gen, dtype=F64).to(dtype)
    loss = (out[0] * wts[..., :3]).sum() + (out[1] * wts[..., 3:4]).sum() + (out[2] * wts[..., 4:]).sum()
    if loss.requires_grad:
        loss.backward()
    grads = [torch.zeros_like(p) if p.grad is None else p.grad for p in params]
    return [o.detach().to(F64) for o in out[:3]], [g.to(F64) for g in grads]


def assert_matches_reference(scene: GaussianScene, dtype=F64, rtol: float = 1e-9, **kw) -> None:
    """Image, alpha, depth and the gradients of means, quats, scales, opacities, SH all match."""
    got_out, got_grad = _run(rasterize, scene, dtype, **kw)
    ref_out, ref_grad = _run(reference_rasterize, scene, F64, **kw)
    for name, g, r in zip(("image", "alpha", "depth"), got_out, ref_out):
        assert torch.isfinite(g).all(), name
        tol = rtol * max(1.0, r.abs().max().item())
        assert (g - r).abs().max().item() <= tol, f"{name}: {(g - r).abs().max().item()} > {tol}"
    for name, g, r in zip(("means", "quats", "scales", "opacities", "sh"), got_grad, ref_grad):
        assert torch.isfinite(g).all(), name
        tol = rtol * max(1.0, r.abs().max().item())
        assert (g - r).abs().max().item() <= tol, f"d/d{name}: {(g - r).abs().max().item()} > {tol}"


BG = torch.tensor([0.2, 0.5, 0.9], dtype=F64)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_random_scene_float64_matches_reference(seed):
    scene = random_scene(120, 40, 36, torch.Generator().manual_seed(seed), scale_range=(0.01, 0.2), dtype=F64)
    assert_matches_reference(scene, background=BG)


def test_random_scene_float32_close_to_reference():
    scene = random_scene(150, 48, 40, torch.Generator().manual_seed(3), scale_range=(0.01, 0.2), dtype=F64)
    assert_matches_reference(scene, dtype=torch.float32, rtol=2e-4, background=BG)


def test_low_sh_degree_and_colors():
    scene = random_scene(60, 32, 32, torch.Generator().manual_seed(4), scale_range=(0.02, 0.2), dtype=F64)
    assert_matches_reference(scene, sh_degree=1)
    cols = torch.rand(60, 3, generator=torch.Generator().manual_seed(5), dtype=F64)
    got, _ = _run(lambda *a, **k: rasterize(*a[:4], None, *a[5:], colors=cols, **k), scene, F64)
    ref, _ = _run(lambda *a, **k: reference_rasterize(*a[:4], None, *a[5:], colors=cols, **k), scene, F64)
    for g, r in zip(got, ref):
        assert torch.allclose(g, r, atol=1e-10)


def test_opacities_near_one_and_antialiased():
    scene = random_scene(80, 40, 36, torch.Generator().manual_seed(6), scale_range=(0.03, 0.3), dtype=F64)
    scene.opacities = 1.0 - torch.rand(80, generator=torch.Generator().manual_seed(8), dtype=F64) * 0.02
    assert_matches_reference(scene, background=BG)
    assert_matches_reference(scene, settings=RasterSettings(antialiased=True))


def test_gaussians_on_tile_borders():
    # means a fraction of a pixel from the 16-px tile edges, support boxes straddling tiles
    gen = torch.Generator().manual_seed(9)
    scene = random_scene(64, 48, 48, gen, scale_range=(0.005, 0.08), dtype=F64)
    f, z = scene.K[0, 0], scene.means[:, 2]
    edge = torch.tensor([16.0, 32.0], dtype=F64)
    u = edge[torch.randint(0, 2, (64,), generator=gen)] + (torch.rand(64, generator=gen, dtype=F64) - 0.5)
    v = edge[torch.randint(0, 2, (64,), generator=gen)] + (torch.rand(64, generator=gen, dtype=F64) - 0.5)
    scene.means = torch.stack([(u - 24) / f * z, (v - 24) / f * z, z], -1)
    img, *_ = rasterize(*scene.args())
    assert img.abs().sum() > 0
    assert_matches_reference(scene)


@pytest.mark.parametrize(
    "settings",
    [RasterSettings(chunk_elements=1), RasterSettings(tile_size=8), RasterSettings(tile_size=5, workers=1),
     RasterSettings(workers=3, chunk_elements=4096)],  # fmt: skip
)
def test_tiles_chunks_and_workers_do_not_change_the_result(settings):
    scene = random_scene(200, 64, 48, torch.Generator().manual_seed(10), scale_range=(0.01, 0.2))
    a, ga = _run(rasterize, scene, torch.float32, settings=settings)
    b, gb = _run(rasterize, scene, torch.float32)
    for x, y in zip(a + ga, b + gb):  # float32 sums in another order: equal to rounding
        assert (x - y).abs().max() <= 1e-5 * max(1.0, y.abs().max().item())


# ---- hard cases, each compared with the reference ----


def _base(n: int = 40, seed: int = 0, width: int = 40, height: int = 32) -> GaussianScene:
    return random_scene(n, width, height, torch.Generator().manual_seed(seed), scale_range=(0.02, 0.2), dtype=F64)


def _set(scene: GaussianScene, i: int, mean=None, scale=None, quat=None, opacity=None) -> None:
    if mean is not None:
        scene.means[i] = torch.tensor(mean, dtype=F64)
    if scale is not None:
        scene.scales[i] = torch.tensor(scale, dtype=F64)
    if quat is not None:
        scene.quats[i] = torch.tensor(quat, dtype=F64)
    if opacity is not None:
        scene.opacities[i] = opacity


def test_behind_camera_and_near_plane():
    s = _base()
    _set(s, 0, mean=[0.0, 0.0, -1.0], scale=[0.5, 0.5, 0.5], opacity=0.9)  # behind
    _set(s, 1, mean=[0.001, 0.0, 0.01], scale=[0.01, 0.01, 0.01], opacity=0.9)  # exactly on the near plane
    _set(s, 2, mean=[0.0005, 0.0003, 0.0101], scale=[1e-4, 1e-4, 1e-4], opacity=0.8)  # just in front
    _set(s, 3, mean=[0.3, 0.0, 0.0102], scale=[1e-3, 1e-3, 1e-3], opacity=0.8)  # just in front, off-screen
    img, alpha, depth, info = rasterize(*s.args())
    assert not info["visible"][0] and not info["visible"][1]
    assert info["visible"][2]
    assert (info["radii"][:2] == 0).all()
    assert_matches_reference(s)


def test_far_away_gaussians():
    s = _base()
    for i in range(5):
        _set(s, i, mean=[0.1 * i - 0.2, 0.05, 4e4], scale=[40.0, 40.0, 40.0], opacity=0.95)
    img, alpha, depth, info = rasterize(*s.args())
    assert info["visible"][:5].all()
    assert_matches_reference(s)
    # the camera's depth range decides: with far below their depth they are culled, in both renderers
    near_view = replace(s.camera, far=1e4)
    _, _, _, info = rasterize(*s.args()[:5], near_view)
    assert not info["visible"][:5].any() and info["visible"][5:].any()
    ref_img, *_ = reference_rasterize(*s.args()[:5], near_view)
    img, *_ = rasterize(*s.args()[:5], near_view)
    assert torch.allclose(img, ref_img, atol=1e-10)
    with pytest.raises(TypeError, match="'camera' must be an exploregs_plugin.cameras.Camera, got Tensor"):
        rasterize(*s.args()[:5], s.viewmat)


def test_scales_from_1e_6_to_1e3_and_anisotropy():
    s = _base(n=30)
    scales = [1e-6, 1e-4, 1e-2, 1.0, 1e3]
    for i, sc in enumerate(scales):
        _set(s, i, scale=[sc, sc, sc])
    _set(s, 5, scale=[1e-5, 0.8, 1e-5], quat=[0.9, 0.1, 0.3, 0.2])  # needle
    _set(s, 6, scale=[2.0, 2.0, 1e-6], quat=[0.7, 0.7, 0.0, 0.1])  # sheet
    _set(s, 7, scale=[1e-3, 3.0, 1e-3], quat=[1.0, 0.0, 0.0, 0.0])
    assert_matches_reference(s, rtol=1e-8)


def test_zero_and_near_zero_quaternions():
    s = _base()
    _set(s, 0, quat=[0.0, 0.0, 0.0, 0.0], scale=[0.3, 0.05, 0.1])
    _set(s, 1, quat=[1e-9, 2e-9, -1e-9, 3e-9], scale=[0.3, 0.05, 0.1])
    _set(s, 2, quat=[1e-13, 0.0, 0.0, 1e-14], scale=[0.3, 0.05, 0.1])
    assert_matches_reference(s)
    # a zero quaternion renders as the identity rotation, with a finite (zero) gradient
    q = s.quats.clone().requires_grad_()
    ident = s.quats.clone()
    ident[0] = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=F64)
    img0, *_ = rasterize(s.means, q, s.scales, s.opacities, s.sh_coeffs, s.camera)
    img1, *_ = rasterize(s.means, ident, s.scales, s.opacities, s.sh_coeffs, s.camera)
    assert torch.allclose(img0, img1, atol=1e-12)
    img0.sum().backward()
    assert torch.isfinite(q.grad).all() and (q.grad[0] == 0).all()
    # for float32, a near-zero quaternion still normalises to a rotation
    s32 = s.to(torch.float32)
    q32 = s32.quats.clone().requires_grad_()
    img, *_ = rasterize(s32.means, q32, s32.scales, s32.opacities, s32.sh_coeffs, s32.camera)  # fmt: skip
    img.sum().backward()
    assert torch.isfinite(q32.grad).all()


def test_opacity_zero_and_one():
    s = _base()
    s.opacities[:10] = 0.0
    s.opacities[10:20] = 1.0
    img, alpha, depth, info = rasterize(*s.args())
    assert not info["visible"][:10].any()
    assert_matches_reference(s)


def test_all_outside_frustum():
    s = _base()
    s.means[:, 0] += 100.0
    img, alpha, depth, info = rasterize(*s.args(), background=torch.tensor([0.1, 0.2, 0.3], dtype=F64))
    assert not info["visible"].any() and info["n_pairs"] == 0
    assert torch.allclose(img, torch.tensor([0.1, 0.2, 0.3], dtype=F64).expand_as(img))
    assert (alpha == 0).all() and (depth == 0).all()
    assert_matches_reference(s)


def test_no_gaussians():
    e = torch.zeros(0, 3, dtype=F64, requires_grad=True)
    q = torch.zeros(0, 4, dtype=F64)
    img, alpha, depth, info = rasterize(e, q, e.detach(), torch.zeros(0, dtype=F64), torch.zeros(0, 16, 3, dtype=F64),
                                        Camera(torch.eye(4, dtype=F64), torch.eye(3, dtype=F64), 20, 10))  # fmt: skip
    assert img.shape == (10, 20, 3) and alpha.shape == depth.shape == (10, 20, 1)
    assert (img == 0).all() and info["means2d"].shape == (0, 2) and info["radii"].shape == (0, 2)
    img.sum().backward()
    assert e.grad.shape == (0, 3)


def test_non_centred_principal_point_and_non_square():
    s = _base(n=80, width=52, height=24)
    s.K[0, 2], s.K[1, 2] = 10.0, 17.5
    assert_matches_reference(s, background=torch.tensor([1.0, 0.0, 0.5], dtype=F64))
    # the guard band follows the principal point: a Gaussian far off the left edge is clamped
    s.means[0] = torch.tensor([-2.0, 0.0, 2.0], dtype=F64)
    s.scales[0] = torch.tensor([1.5, 1.5, 1.5], dtype=F64)
    assert_matches_reference(s)


def test_single_opaque_gaussian():
    s = _base(n=1)
    _set(s, 0, mean=[0.01, -0.02, 3.0], scale=[0.3, 0.3, 0.3], opacity=1.0, quat=[1.0, 0.0, 0.0, 0.0])
    img, alpha, depth, info = rasterize(*s.args())
    assert math.isclose(alpha.max().item(), 0.99, rel_tol=1e-12)  # alpha_max clamp
    assert torch.allclose(depth[alpha > 0.5], torch.full_like(depth[alpha > 0.5], 3.0))
    assert_matches_reference(s)


def test_bad_input_names_the_argument():
    s = _base(n=3)
    with pytest.raises(ValueError, match="quats"):
        rasterize(s.means, s.quats[:, :3], s.scales, s.opacities, s.sh_coeffs, Camera(s.viewmat, s.K, 8, 8))
    with pytest.raises(ValueError, match="sh_degree"):
        rasterize(*s.args(), sh_degree=4)
    with pytest.raises(ValueError, match="colors"):
        rasterize(s.means, s.quats, s.scales, s.opacities, None, Camera(s.viewmat, s.K, 8, 8))


def test_windowed_reference_is_a_crop_and_threads_are_restored():
    s = _base(n=60, width=40, height=32)
    full, *_ = reference_rasterize(*s.args())
    win, *_ = reference_rasterize(*s.args(), window=(7, 5, 20, 16))
    assert torch.allclose(win, full[5:21, 7:27], atol=1e-14)
    threads = torch.get_num_threads()
    m = s.means.clone().requires_grad_()
    img, *_ = rasterize(m, *s.args()[1:])
    img.sum().backward()
    assert torch.get_num_threads() == threads and m.grad.abs().sum() > 0


def test_the_compositor_uses_the_callers_thread_count():
    from exploregs_plugin.rasterizer.composite import _workers, single_threaded_ops

    before = torch.get_num_threads()
    try:
        for n in (1, 3):
            torch.set_num_threads(n)
            with single_threaded_ops():  # rasterize runs the compositor inside this block
                assert torch.get_num_threads() == 1
                assert _workers(RasterSettings(), torch.device("cpu")) == n
                assert _workers(RasterSettings(workers=2), torch.device("cpu")) == 2
            assert torch.get_num_threads() == n
        assert _workers(RasterSettings(), torch.device("meta")) == 1  # a GPU-like device: one thread
    finally:
        torch.set_num_threads(before)


@pytest.mark.parametrize("dtype, bits", [(torch.float32, torch.int32), (torch.float64, torch.int64)])
def test_the_few_operator_rotation_is_the_same_bits(dtype, bits):
    """quats_to_rotmats(few_operators=True), the split's form, gives the forty-operator form's
    floats bit for bit, signed zeros included: random quaternions over twelve orders of magnitude,
    the zero quaternion, one below the identity threshold, axis-aligned ones with -0 components."""
    from exploregs_plugin.rasterizer.projection import quats_to_rotmats

    g = torch.Generator().manual_seed(7)
    q = torch.randn(512, 4, generator=g, dtype=dtype) * torch.logspace(-6, 6, 512, dtype=dtype)[:, None]
    special = torch.tensor([[0.0, 0.0, 0.0, 0.0], [1e-13, 0.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0], [-0.5, -0.0, 0.0, 0.3],
                            [0.0, -1.0, -0.0, 0.0], [-0.0, 0.0, 0.0, -2.0]], dtype=dtype)  # fmt: skip
    q = torch.cat([special, q])
    plain, few = quats_to_rotmats(q), quats_to_rotmats(q, few_operators=True)
    assert torch.equal(plain.view(bits), few.view(bits))
    assert torch.equal(plain[0], torch.eye(3, dtype=dtype)) and torch.equal(plain[1], torch.eye(3, dtype=dtype))
    assert (plain.view(bits) == torch.tensor(-0.0, dtype=dtype).view(bits)).any()  # a -0 entry is compared too
