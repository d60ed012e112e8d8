"""The compiled CPU backend (``--model.raster.backend cpp``) against the torch reference: it builds,
draws the same image with the same gradients (the dense float64 reference tests run on both
backends through the ``raster_backend`` fixture), gives the same bits at any thread count, and
trains to the same result; a machine that cannot build it gets one clear line."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from dataclasses import replace

import pytest
import torch

from exploregs_plugin.bench.components.raster_scenes import GaussianScene, random_scene
from exploregs_plugin.rasterizer import BackendError, RasterSettings, backend_line, backend_problem, rasterize
from exploregs_plugin.rasterizer import backends
from exploregs_plugin.rasterizer.cpp_backend import composite_cpp, cpp_problem, project_cpp, sh_colors_cpp
from exploregs_plugin.rasterizer.reference import reference_rasterize

F64 = torch.float64
TORCH, CPP = RasterSettings(backend="torch"), RasterSettings(backend="cpp")
HAS_COMPILER = shutil.which(os.environ.get("CXX", "c++")) is not None
needs_cpp = pytest.mark.skipif(not HAS_COMPILER, reason="no C++ compiler on this machine")


def _outputs_and_grads(scene: GaussianScene, settings: RasterSettings, dtype=torch.float32, **kw):
    """Image, alpha, depth, visibility and the gradients of every parameter and of means2d for a
    fixed random weighting of all outputs."""
    params = [t.detach().to(dtype).clone().requires_grad_() for t in
              (scene.means, scene.quats, scene.scales, scene.opacities, scene.sh_coeffs)]  # fmt: skip
    image, alpha, depth, info = rasterize(*params, scene.camera.to(dtype), settings=settings, **kw)  # fmt: skip
    info["means2d"].retain_grad()
    wts = torch.randn(scene.height, scene.width, 5, generator=torch.Generator().manual_seed(7), dtype=F64).to(dtype)
    loss = (image * wts[..., :3]).sum() + (alpha * wts[..., 3:4]).sum() + (depth * wts[..., 4:]).sum()
    loss.backward()
    outs = {"image": image, "alpha": alpha, "depth": depth, "radii": info["radii"], "visible": info["visible"]}
    if "visibility" in info:
        outs["visibility"] = info["visibility"]
    grads = {n: p.grad for n, p in zip(("means", "quats", "scales", "opacities", "sh"), params)}
    grads["means2d"] = info["means2d"].grad
    return {k: v.detach() for k, v in outs.items()}, grads, info["n_pairs"]


def _rel(a: torch.Tensor, b: torch.Tensor) -> float:
    """max |a - b| / max |b| (the scale of a gradient is its largest entry)."""
    return ((a.double() - b.double()).abs().max() / b.double().abs().max().clamp_min(1e-30)).item()


@needs_cpp
def test_the_cpp_backend_builds_on_this_machine():
    assert cpp_problem() is None
    assert backends.resolve_backend(RasterSettings(), torch.device("cpu")) == "cpp"
    assert backend_line(RasterSettings(), torch.device("cpu")) == "renderer: cpp (compiled CPU kernels)"


SCENES = [(0, 3000, (160, 120)), (1, 800, (97, 61)), (2, 5000, (128, 128))]


@needs_cpp
@pytest.mark.parametrize("seed,n,size", SCENES)
def test_float64_image_and_every_gradient_agree_with_torch(seed, n, size):
    scene = random_scene(n, *size, torch.Generator().manual_seed(seed), scale_range=(0.005, 0.3), dtype=F64)
    bg = torch.tensor([0.2, 0.5, 0.9], dtype=F64)
    got, got_g, pairs = _outputs_and_grads(scene, replace(CPP, visibility_stats=True), F64, background=bg)
    ref, ref_g, ref_pairs = _outputs_and_grads(scene, replace(TORCH, visibility_stats=True), F64, background=bg)
    assert 0.5 * ref_pairs < pairs < ref_pairs  # the compiled binning leaves out the tiles the ellipses miss
    assert torch.equal(got["radii"], ref["radii"]) and torch.equal(got["visible"], ref["visible"])
    for name in ("image", "alpha", "depth", "visibility"):
        assert _rel(got[name], ref[name]) <= 1e-10, name
    for name in ref_g:
        assert torch.isfinite(got_g[name]).all(), name
        assert _rel(got_g[name], ref_g[name]) <= 1e-10, f"d/d{name}: {_rel(got_g[name], ref_g[name]):.2e}"


@needs_cpp
@pytest.mark.parametrize("seed,n,size", SCENES)
def test_float32_is_as_accurate_as_the_torch_reference(seed, n, size):
    """In float32 both backends round: each is within a few 1e-5 of the float64 result (its
    largest entry's scale), in other summation orders. The compiled one may not be worse."""
    scene = random_scene(n, *size, torch.Generator().manual_seed(seed), scale_range=(0.005, 0.3))
    truth, truth_g, _ = _outputs_and_grads(scene, CPP, F64)
    got, got_g, _ = _outputs_and_grads(scene, CPP)
    ref, ref_g, _ = _outputs_and_grads(scene, TORCH)
    for name in ("image", "alpha", "depth"):
        assert _rel(got[name], truth[name]) <= 1.5 * _rel(ref[name], truth[name]) + 1e-6, name
        assert _rel(got[name], ref[name]) <= 5e-5, name
    for name in ref_g:
        err, ref_err = _rel(got_g[name], truth_g[name]), _rel(ref_g[name], truth_g[name])
        # The compiled backend sums a Gaussian's pixels one after another, torch in blocked matrix
        # products whose blocks follow the chunking: torch's error moves with its chunks (d/dscales
        # here: 1.4e-5 to 2.4e-5), the compiled one stays 3.9e-5. Either way a few 1e-5.
        assert err <= max(2.0 * ref_err, 5e-5), f"d/d{name}: {err:.1e} against the reference's {ref_err:.1e}"
        assert _rel(got_g[name], ref_g[name]) <= 5e-5, f"d/d{name}"


@needs_cpp
def test_same_bits_at_1_2_and_4_threads():
    scene = random_scene(4000, 128, 96, torch.Generator().manual_seed(5), scale_range=(0.005, 0.3))
    before = torch.get_num_threads()
    runs = []
    try:
        for threads in (1, 2, 4):
            torch.set_num_threads(threads)
            runs.append(_outputs_and_grads(scene, replace(CPP, visibility_stats=True)))
    finally:
        torch.set_num_threads(before)
    (out1, grad1, _), rest = runs[0], runs[1:]
    for out, grad, _ in rest:
        for name in out1:
            assert torch.equal(out[name], out1[name]), name
        for name in grad1:
            assert torch.equal(grad[name], grad1[name]), f"d/d{name}"


def _hard_scene() -> GaussianScene:
    """Equal depths, a Gaussian covering the whole image, one at the camera centre, a needle and
    a saturated one, over random ones."""
    s = random_scene(30, 40, 32, torch.Generator().manual_seed(3), scale_range=(0.02, 0.2), dtype=F64)
    s.means[0:3] = torch.tensor([[0.1, 0.0, 3.0], [-0.1, 0.05, 3.0], [0.0, -0.1, 3.0]], dtype=F64)  # equal depths
    s.opacities[0:3] = 0.7
    s.means[3], s.scales[3], s.opacities[3] = torch.tensor([0.0, 0.0, 5.0], dtype=F64), 20.0, 0.3  # whole image
    s.means[4] = -(s.viewmat[:3, :3].T @ s.viewmat[:3, 3])  # the camera centre
    s.scales[5] = torch.tensor([1e-6, 1e-6, 2.0], dtype=F64)  # needle
    s.opacities[6] = 1.0
    return s


@needs_cpp
@pytest.mark.parametrize("antialiased", [False, True])
def test_hard_cases_match_the_float64_reference(antialiased):
    scene = _hard_scene()
    settings = replace(CPP, antialiased=antialiased)
    got, got_g, _ = _outputs_and_grads(scene, settings, dtype=F64)
    params = [t.detach().clone().requires_grad_() for t in
              (scene.means, scene.quats, scene.scales, scene.opacities, scene.sh_coeffs)]  # fmt: skip
    ref = reference_rasterize(*params, scene.camera, settings=settings)
    wts = torch.randn(scene.height, scene.width, 5, generator=torch.Generator().manual_seed(7), dtype=F64)
    ((ref[0] * wts[..., :3]).sum() + (ref[1] * wts[..., 3:4]).sum() + (ref[2] * wts[..., 4:]).sum()).backward()
    assert got["image"].abs().sum() > 0
    for name, r in zip(("image", "alpha", "depth"), ref[:3]):
        assert (got[name] - r.detach()).abs().max() <= 1e-9 * max(1.0, r.abs().max().item()), name
    for name, p in zip(("means", "quats", "scales", "opacities", "sh"), params):
        assert torch.isfinite(got_g[name]).all(), name
        assert (got_g[name] - p.grad).abs().max() <= 1e-9 * max(1.0, p.grad.abs().max().item()), f"d/d{name}"


@needs_cpp
def test_float64_gradcheck_of_each_kernel():
    gen = torch.Generator().manual_seed(11)
    scene = random_scene(12, 20, 16, gen, scale_range=(0.05, 0.3), sh_degree=3, focal=24.0, dtype=F64)
    # projection: every Gaussian in front of the camera, inside the guard band
    inputs = [t.clone().requires_grad_() for t in (scene.means, scene.quats, scene.scales, scene.opacities)]
    for aa in (False, True):
        settings = replace(CPP, antialiased=aa)

        def project(means, quats, scales, opacities):
            p = project_cpp(means, quats, scales, opacities, scene.viewmat, scene.K, 20, 16, 0.01, 1e10, settings, 2)
            return p.means2d, p.conics, p.opacities, p.depths

        assert torch.autograd.gradcheck(project, inputs, eps=1e-6, atol=1e-6)
    # SH colours of a subset of rows (colours kept away from the clamp at 0)
    coeffs = scene.sh_coeffs.clone()
    coeffs[:, 0] = 2.0
    visible = torch.zeros(scene.means.shape[0], dtype=torch.bool)
    visible[[0, 3, 4, 7, 11]] = True
    center = -(scene.viewmat[:3, :3].T @ scene.viewmat[:3, 3])
    for degree in range(4):
        colours = sh_colors_cpp(coeffs, scene.means, visible, center, degree, 2)
        assert colours.shape == (scene.means.shape[0], 3) and not colours[~visible].any()  # 0 where not drawn
        assert torch.autograd.gradcheck(
            lambda k, m: sh_colors_cpp(k, m, visible, center, degree, 2),
            [coeffs.clone().requires_grad_(), scene.means.clone().requires_grad_()], eps=1e-6, atol=1e-6)


@needs_cpp
def test_float64_gradcheck_of_the_compositor():
    """Four overlapping Gaussians on a 12 x 10 image (two tiles of 8), opacities and positions
    chosen so that no pair sits at the box edge, the 1/255 skip or the transmittance stop."""
    from exploregs_plugin.rasterizer.cpp_backend import CppBins

    means2d = torch.tensor([[4.3, 4.1], [6.2, 5.4], [7.7, 3.9], [5.1, 6.6]], dtype=F64)
    conics = torch.tensor([[0.30, 0.05, 0.25], [0.20, -0.04, 0.35], [0.5, 0.1, 0.3], [0.25, 0.0, 0.25]], dtype=F64)
    opac = torch.tensor([0.6, 0.5, 0.8, 0.4], dtype=F64)
    feats = torch.rand(4, 4, generator=torch.Generator().manual_seed(2), dtype=F64)
    support = torch.full((4, 2), 30.0, dtype=F64)  # boxes wider than the image: no pair on an edge
    depths = torch.tensor([1.0, 2.0, 3.0, 4.0], dtype=F64)
    settings = replace(CPP, tile_size=8, alpha_min=1e-12, transmittance_min=1e-12)
    bins = CppBins(means2d, support, depths, 12, 10, 8)

    def comp(m, c, o, f):
        return composite_cpp(m, c, o, f, support, bins, settings, 2)[0]

    args = [t.clone().requires_grad_() for t in (means2d, conics, opac, feats)]
    assert torch.autograd.gradcheck(comp, args, eps=1e-6, atol=1e-7)


@pytest.mark.parametrize("backend", ["torch", "cpp"])
def test_the_coefficients_as_the_models_pair_render_and_differentiate_as_their_concatenation(backend):
    """rasterize takes (sh0, shN) as the model keeps them: the same image and the same gradients,
    bit for bit, as with the [N, 16, 3] concatenation; on the compiled path each gradient is made in
    its parameter's layout (contiguous: autograd takes it without a copy)."""
    if backend == "cpp" and not HAS_COMPILER:
        pytest.skip("no C++ compiler on this machine")
    scene = random_scene(60, 48, 40, torch.Generator().manual_seed(11), sh_degree=3)
    settings = RasterSettings(backend=backend)
    sh0 = scene.sh_coeffs[:, :1].clone().requires_grad_()
    shN = scene.sh_coeffs[:, 1:].clone().requires_grad_()
    joined = scene.sh_coeffs.clone().requires_grad_()
    weights = torch.randn(40, 48, 3, generator=torch.Generator().manual_seed(3))
    pair_image, *_ = rasterize(scene.means, scene.quats, scene.scales, scene.opacities, (sh0, shN), scene.camera,
                               settings=settings)
    joined_image, *_ = rasterize(scene.means, scene.quats, scene.scales, scene.opacities, joined, scene.camera,
                                 settings=settings)
    (pair_image * weights).sum().backward()
    (joined_image * weights).sum().backward()
    assert torch.equal(pair_image, joined_image) and joined.grad.abs().sum() > 0
    assert torch.equal(sh0.grad, joined.grad[:, :1]) and torch.equal(shN.grad, joined.grad[:, 1:])
    if backend == "cpp":
        assert sh0.grad.is_contiguous() and shN.grad.is_contiguous()
    with pytest.raises(ValueError, match="shN"):
        rasterize(scene.means, scene.quats, scene.scales, scene.opacities, (sh0, shN[:, :, :2]), scene.camera,
                  settings=settings)


@needs_cpp
@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_the_binning_takes_the_drawn_rows_in_the_order_of_torchs_stable_argsort(dtype):
    """The kernel sorts the drawn rows by depth itself (a radix sort of the floats' bits): each
    tile's list is their order in torch.argsort(depths, stable=True), ties by row, for depths with
    many ties, of both signs and of every size; rows not drawn are in no list."""
    from exploregs_plugin.rasterizer.cpp_backend import CppBins

    g = torch.Generator().manual_seed(4)
    n = 3000
    means2d = (torch.rand(n, 2, generator=g, dtype=F64) * torch.tensor([40.0, 30.0], dtype=F64)).to(dtype)
    support = torch.full((n, 2), 6.0, dtype=dtype)
    depths = torch.cat([
        torch.randint(1, 6, (n // 3,), generator=g).to(F64),  # ties: five values
        torch.rand(n // 3, generator=g, dtype=F64) * 1e-3,  # small, and their float32 rounding ties some
        (torch.rand(n - 2 * (n // 3), generator=g, dtype=F64) - 0.5) * 2e6,  # both signs, large
    ]).to(dtype)
    visible = torch.rand(n, generator=g) < 0.8
    bins = CppBins(means2d, support, depths, 40, 30, 8, visible)
    rank = torch.empty(n, dtype=torch.long)
    rank[torch.argsort(depths, stable=True)] = torch.arange(n)
    off, pairs = bins.tile_offsets, bins.pair_gauss.long()
    assert not visible[pairs].logical_not().any() and pairs.numel() > n
    for t in range(off.numel() - 1):
        tile = pairs[off[t]:off[t + 1]]
        assert torch.equal(rank[tile], rank[tile].sort().values)  # front to back, ties by row
    assert torch.equal(bins.gauss_count > 0, visible)


def test_a_machine_without_a_compiler_gets_one_line_and_auto_falls_back(monkeypatch):
    reason = "no C++ compiler found (looked for 'c++'; install g++ or set CXX)"
    monkeypatch.setattr(backends, "cpp_problem", lambda: reason)
    backends.backend_problem.cache_clear()
    backends._resolve.cache_clear()
    try:
        problem = backend_problem(CPP, torch.device("cpu"))
        assert problem == f"--model.raster.backend cpp cannot run here: {reason}"
        assert backends.resolve_backend(RasterSettings(), torch.device("cpu")) == "torch"
        assert backend_line(RasterSettings(), torch.device("cpu")) == f"renderer: torch (cpp not used: {reason})"
        s = random_scene(5, 16, 16, torch.Generator().manual_seed(0))
        with pytest.raises(BackendError, match="cannot run here: no C"):
            rasterize(*s.args(), settings=CPP)
        assert rasterize(*s.args())[0].shape == (16, 16, 3)  # auto draws with the reference
        assert "cpp is the compiled CPU compositor" in backend_problem(CPP, torch.device("cuda"))
    finally:
        backends.backend_problem.cache_clear()
        backends._resolve.cache_clear()


def test_a_failing_build_is_one_line_not_a_traceback(tmp_path):
    """A compiler that fails (here: `false`) in a fresh extension cache: cpp_problem is one line."""
    env = dict(os.environ, CXX=shutil.which("false") or "/bin/false", TORCH_EXTENSIONS_DIR=str(tmp_path))
    code = "from exploregs_plugin.rasterizer.cpp_backend import cpp_problem; print('@' + cpp_problem())"
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    lines = out.stdout.strip().splitlines()
    assert lines[-1].startswith("@the C++ kernels did not build: ") and len(lines) == 1, lines
    assert "Traceback" not in out.stderr


def _train(tmp_path, method: str, backend: str, threads: int, steps: int, schedule, cuts: bool = True):
    """A short tiny run (``cuts`` False: without the strategy's cuts, which keep or drop a row at
    a threshold that a rounding can move); (test PSNR, the trained parameters)."""
    from exploregs_plugin.method_configs import get_method

    config = get_method(method).config
    model = replace(config.pipeline.model, raster=replace(config.pipeline.model.raster, backend=backend))
    strategy = config.pipeline.strategy if cuts else replace(config.pipeline.strategy, final_weight_share=0.0)
    config = replace(config, data="builtin:tiny", max_steps=steps, run_dir=tmp_path / f"{backend}-{threads}",
                     quiet=True, tensorboard=False, eval_count=1, save_eval_images=False, checkpoint_every=10_000,
                     schedule=schedule, num_threads=threads,
                     pipeline=replace(config.pipeline, model=model, strategy=strategy))
    before = torch.get_num_threads()
    try:
        trainer = config.setup()
        metrics = trainer.train()
    finally:
        torch.set_num_threads(before)
    return metrics["psnr"], {k: v.detach().clone() for k, v in trainer.pipeline.params.items()}


@needs_cpp
def test_a_training_run_with_cpp_is_the_same_at_1_and_2_threads(tmp_path, tiny_scene_dir):
    """Densification, random seeding and splitting included: the same Gaussians, bit for bit."""
    from exploregs_plugin.schedule import ScheduleConfig

    schedule = ScheduleConfig(min_refine_every=10)
    # the thread pool started at two threads, as any earlier computation starts it: torch's fused
    # CPU Adam on two threads then changed the last bits (it runs on one: OptimizerSet.step)
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    (torch.ones(1 << 22) * 2.0).sum()
    torch.set_num_threads(before)
    psnr1, params1 = _train(tmp_path, "exploregs-seedsplit", "cpp", 1, 30, schedule)
    psnr2, params2 = _train(tmp_path, "exploregs-seedsplit", "cpp", 2, 30, schedule)
    assert psnr1 == psnr2
    for name in params1:
        assert torch.equal(params1[name], params2[name]), name


@needs_cpp
def test_a_run_of_more_gaussians_than_torchs_grain_is_the_same_at_1_and_2_threads(tmp_path, tiny_scene_dir):
    """torch cuts an elementwise operator over more than 32,768 elements into one chunk per
    thread, and a chunk's last elements go through the scalar exp, sigmoid, ... whose last bit
    can differ from the vectorised one: the cut moves with the thread count. The README's job
    crossed that size at step 700 and parted ways on 1 and 2 threads. Here 40,003 Gaussians
    (chunks of 20,002 opacities, not a whole number of vectors) from the first step, refined every
    3 steps, 8 steps from one snapshot on 1 and on 2 threads: with torch's operators on the run's
    threads the two differed."""
    import copy

    from exploregs_plugin.method_configs import get_method
    from exploregs_plugin.schedule import ScheduleConfig

    config = get_method("exploregs-seedsplit").config
    datamanager = replace(config.pipeline.datamanager, random_init=True, n_random_points=40_003)
    config = replace(config, data="builtin:tiny", max_steps=8, run_dir=tmp_path / "run", quiet=True,
                     tensorboard=False, schedule=ScheduleConfig(refine_start_frac=0.0, min_refine_every=3),
                     pipeline=replace(config.pipeline, datamanager=datamanager))
    pipeline = config.setup().pipeline  # one setup: 40,003 initial points take seconds to place
    assert pipeline.model.num_gaussians > 32_768
    snapshot = copy.deepcopy(pipeline.state_dict())
    before = torch.get_num_threads()
    trained = []
    try:
        for threads in (1, 2):
            torch.set_num_threads(threads)
            pipeline.load_state_dict(copy.deepcopy(snapshot))
            losses = [pipeline.train_step(step)["loss"] for step in range(8)]
            trained.append((losses, {k: v.detach().clone() for k, v in pipeline.params.items()}))
    finally:
        torch.set_num_threads(before)
    (losses1, params1), (losses2, params2) = trained
    assert params1["means"].shape[0] != 40_003  # the refinements changed the set
    assert all(torch.equal(a, b) for a, b in zip(losses1, losses2))
    for name in params1:
        assert torch.equal(params1[name], params2[name]), name


@needs_cpp
def test_a_short_training_run_with_cpp_matches_torch(tmp_path, tiny_scene_dir):
    """The same fixed set of Gaussians (no densification in these steps, no cut) optimised with
    either backend reaches the same PSNR. With densification or a cut the runs part ways: a float32
    rounding moves a 2D-mean gradient across the threshold, or a checked cut's deficit across its
    tolerance, and the sets differ (docs/rasterizer.md)."""
    from exploregs_plugin.schedule import ScheduleConfig

    schedule = ScheduleConfig(refine_start_frac=1.0, min_refine_every=10_000)
    psnr_t, params_t = _train(tmp_path, "exploregs-default", "torch", 2, 40, schedule, cuts=False)
    psnr_c, params_c = _train(tmp_path, "exploregs-default", "cpp", 2, 40, schedule, cuts=False)
    assert params_c["means"].shape == params_t["means"].shape
    assert abs(psnr_c - psnr_t) <= 0.05, (psnr_c, psnr_t)
    assert psnr_c > 13.5  # it trained: one step gives 11.6 dB here, 40 steps 15.2 dB


@needs_cpp
def test_a_built_extension_loads_past_a_leftover_build_lock(tmp_path, monkeypatch):
    """A process killed while torch's loader held the build lock leaves the lock file behind; a
    finished build is imported without waiting on it."""
    from exploregs_plugin.kernels.build import _build_dir, extension_name

    assert cpp_problem() is None
    name = extension_name()
    built = _build_dir(name)
    env = dict(os.environ, TORCH_EXTENSIONS_DIR=str(tmp_path))
    # the folder a process with that cache would build in (torch reads the variable at each call)
    with monkeypatch.context() as patch:
        patch.setenv("TORCH_EXTENSIONS_DIR", str(tmp_path))
        target = tmp_path / os.path.relpath(_build_dir(extension_name()), tmp_path)
    target.mkdir(parents=True, exist_ok=True)
    shutil.copy2(built / f"{name}.so", target / f"{name}.so")
    (target / "lock").touch()  # held by no one
    code = "from exploregs_plugin.kernels import cpp_problem; print('@', cpp_problem())"
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=60)
    assert out.stdout.strip().splitlines()[-1] == "@ None", out.stderr


def test_the_build_says_each_unit_as_it_finishes(tmp_path, monkeypatch):
    """While the kernels build, a line per compiled unit (its object file appears) with the elapsed
    time, and a line between units when one takes long; a unit left by an interrupted build is
    not announced again."""
    import io
    import time

    from exploregs_plugin.kernels import build

    monkeypatch.setattr(build, "PROGRESS_SECONDS", 0.6)
    (tmp_path / "sh_cpu.o").touch()  # left by an interrupted build
    out = io.StringIO()
    monkeypatch.setattr(build.sys, "stderr", out)
    with build._BuildProgress(tmp_path, ["composite_cpu", "sh_cpu", "bindings"]) as progress:
        time.sleep(1.4)  # nothing finishes: the "compiling..." line
        (tmp_path / "bindings.o").touch()
        time.sleep(1.0)
    lines = out.getvalue().splitlines()
    assert progress.done == {"sh_cpu", "bindings"}
    assert any(ln.endswith("compiling... 1 of 3 units done") for ln in lines), lines
    compiled = [ln for ln in lines if "compiled" in ln]
    assert len(compiled) == 1 and re.fullmatch(r"  \[0:0\d\] compiled bindings \(2 of 3 units\)", compiled[0]), lines
