"""The device option on a machine without CUDA: resolution and its errors, checkpoints made on
another device, --device cpu changing nothing, and code that follows its inputs' device.

"Follows its inputs' device" is checked without a GPU: with torch's default device set to
``meta``, any tensor made without an explicit device lands on ``meta``, and the first operation
that mixes it with the CPU inputs fails. A run that passes creates every tensor where its inputs
live, which is what running on CUDA needs.
"""

from __future__ import annotations

import contextlib
import sys
from dataclasses import replace
from pathlib import Path

import pytest
import torch

from exploregs_plugin.cameras import Camera
from exploregs_plugin.bench.components.raster_scenes import random_scene
from exploregs_plugin.runtime.device import DeviceError, make_generator, resolve_device, restore_generator, to_device
from exploregs_plugin.evaluation.metrics import evaluate
from exploregs_plugin.io.checkpoint import latest_checkpoint, load_checkpoint
from exploregs_plugin.method_configs import get_method
from exploregs_plugin.rasterizer import BackendError, RasterSettings, backend_problem, rasterize, rasterize_branched
from exploregs_plugin.schedule import ScheduleConfig
from exploregs_plugin.engine.trainer import Trainer, TrainerConfig

NO_CUDA = not torch.cuda.is_available()


@contextlib.contextmanager
def foreign_default_device():
    """Tensors made without a device go to ``meta`` inside the block (thread-local: keep the
    compositor on one worker)."""
    torch.set_default_device("meta")
    try:
        yield
    finally:
        torch.set_default_device(None)


def test_device_names_resolve_or_fail_in_one_line():
    assert resolve_device("cpu") == torch.device("cpu")
    assert resolve_device("auto") == torch.device("cuda" if torch.cuda.is_available() else "cpu")
    assert resolve_device(" CPU ") == torch.device("cpu")
    for bad in ("gpu", "cuda:x", "tpu"):
        with pytest.raises(DeviceError, match="is not a device; choose auto"):
            resolve_device(bad)
    if NO_CUDA:
        for name in ("cuda", "cuda:0"):
            with pytest.raises(DeviceError, match=r"no CUDA device is available here .*use --device cpu or auto") as err:
                resolve_device(name)
            assert "\n" not in str(err.value)


@pytest.mark.skipif(not NO_CUDA, reason="checks the error on a machine without CUDA")
def test_cli_device_cuda_without_cuda_is_one_line(tmp_path, capsys):
    from exploregs_plugin.scripts import run_cli
    from exploregs_plugin.scripts.train import main

    with pytest.raises(SystemExit) as exit_:
        run_cli("eg-train", main, ["exploregs-default", "--data", "builtin:tiny", "--device", "cuda",
                                   "--output-dir", str(tmp_path)])
    assert exit_.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("eg-train: error: --device cuda: no CUDA device is available here")


def test_gsplat_backend_problems_say_what_to_do():
    gsplat = RasterSettings(backend="gsplat")
    assert backend_problem(RasterSettings(), torch.device("cpu")) is None
    problem = backend_problem(gsplat, torch.device("cpu"))
    assert "--device cuda" in problem and "--model.raster.backend torch" in problem
    from exploregs_plugin.engine.pipeline import PipelineConfig

    with pytest.raises(BackendError, match="renders with CUDA kernels"):  # refused before any data is read
        PipelineConfig(model=replace(PipelineConfig().model, raster=gsplat)).setup(
            ScheduleConfig().resolve(10), 0, torch.device("cpu"))
    odd = RasterSettings(backend="gsplat", sigma_radius=2.0)
    if not NO_CUDA:
        assert "sigma-radius" in backend_problem(odd, torch.device("cuda"))
    s = random_scene(20, 32, 24, torch.Generator().manual_seed(0))
    with pytest.raises(BackendError, match="--model.raster.backend torch"):
        rasterize_branched(s.means, s.quats, s.scales, s.opacities, s.sh_coeffs, Camera(s.viewmat, s.K, 32, 24),
                           means_cov=s.means.clone(), means_sh=s.means, settings=gsplat)


def test_branched_rendering_under_auto_renders_with_the_reference_where_auto_would_pick_gsplat(monkeypatch):
    # On a GPU ``auto`` picks gsplat, whose kernels take one means tensor; the branch analysis and
    # the branch ablation (default backend) must still render there, with the torch reference.
    import importlib

    rasterize_module = importlib.import_module("exploregs_plugin.rasterizer.rasterize")
    s = random_scene(40, 32, 24, torch.Generator().manual_seed(1))
    camera = Camera(s.viewmat, s.K, 32, 24)
    shifted = s.means + 0.01

    def branched(settings):
        return rasterize_branched(s.means, s.quats, s.scales, s.opacities, s.sh_coeffs, camera,
                                  means_cov=shifted, means_sh=s.means, settings=settings)

    expected = branched(RasterSettings(backend="torch"))
    plain = rasterize(s.means, s.quats, s.scales, s.opacities, s.sh_coeffs, camera, settings=RasterSettings(backend="torch"))
    assert not torch.equal(expected[0], plain[0])  # the separate covariance path changed the image
    monkeypatch.setattr(rasterize_module, "resolve_backend", lambda settings, device: "gsplat")
    image, alpha, depth, _ = branched(RasterSettings())
    assert torch.equal(image, expected[0]) and torch.equal(alpha, expected[1]) and torch.equal(depth, expected[2])
    with pytest.raises(BackendError, match="--model.raster.backend torch"):  # an explicit gsplat is refused
        branched(RasterSettings(backend="gsplat"))


def test_rasterizer_follows_the_device_of_its_inputs():
    s = random_scene(300, 64, 48, torch.Generator().manual_seed(0))
    params = [t.clone().requires_grad_(True) for t in (s.means, s.quats, s.scales, s.opacities, s.sh_coeffs)]
    settings = RasterSettings(workers=1)
    image, alpha, depth, info = rasterize(*params, s.camera,
                                          background=torch.ones(3), settings=settings)
    (image.sum() + alpha.sum() + depth.sum()).backward()
    expected = [p.grad.clone() for p in params]
    for p in params:
        p.grad = None
    with foreign_default_device():
        image2, alpha2, depth2, _ = rasterize(*params, s.camera,
                                              background=torch.ones(3, device="cpu"), settings=settings)
        (image2.sum() + alpha2.sum() + depth2.sum()).backward()
    assert image2.device.type == "cpu" and torch.equal(image2, image) and torch.equal(depth2, depth)
    for p, g in zip(params, expected):
        assert torch.equal(p.grad, g)


@pytest.mark.parametrize("method", ["exploregs-seedsplit", "exploregs-mcmc", "exploregs-ray"])
def test_training_steps_and_evaluation_follow_the_run_device(method, tiny_scene_dir):
    base = get_method(method).config
    config = replace(base, data="builtin:tiny", max_steps=24,
                     schedule=ScheduleConfig(min_refine_every=5, min_reset_every=10))
    config.pipeline.model.raster = RasterSettings(workers=1)
    pipeline = config.pipeline.setup(config.schedule.resolve(24), 0, torch.device("cpu"))
    totals: dict[str, int] = {}
    with foreign_default_device():
        for step in range(24):
            for op, n in pipeline.train_step(step)["counts"].items():
                totals[op] = totals.get(op, 0) + n
        metrics = evaluate(pipeline.model, pipeline.datamanager)
    assert metrics["psnr"] > 0 and all(p.device.type == "cpu" for p in pipeline.params.values())
    # the set changed inside the block: growth, exploration and noise all ran there
    changed = {op for op, n in totals.items() if n > 0}
    expected = {"exploregs-seedsplit": {"cloned", "split", "random_split", "seeded", "opacity_reset"},
                "exploregs-mcmc": {"added", "perturbed"}, "exploregs-ray": {"split", "perturbed"}}[method]
    assert expected <= changed, totals


def test_device_cpu_is_the_default_run_bit_for_bit(tmp_path, tiny_scene_dir):
    def run(device: str, name: str) -> dict[str, torch.Tensor]:
        config = TrainerConfig(data="builtin:tiny", max_steps=25, device=device, run_dir=tmp_path / name, quiet=True,
                               tensorboard=False, eval_count=1, save_eval_images=False,
                               schedule=ScheduleConfig(min_refine_every=10))
        trainer = Trainer(config)
        trainer.train()
        assert trainer.device == torch.device("cpu") or device == "auto"
        return {k: v.detach() for k, v in trainer.pipeline.params.items()}

    explicit = run("cpu", "cpu")
    if NO_CUDA:
        auto = run("auto", "auto")
        assert explicit.keys() == auto.keys() and all(torch.equal(explicit[k], auto[k]) for k in explicit)
    assert explicit["means"].shape[0] > 0


def _save_as_if_from_cuda(payload: dict, path: Path, monkeypatch) -> None:
    """torch.save ``payload`` with every storage tagged ``cuda:0``, as a GPU run writes it (the
    file then needs map_location to load on a machine without CUDA)."""
    import torch.serialization as ser

    with monkeypatch.context() as patch:
        patch.setattr(ser, "location_tag", lambda storage: "cuda:0")
        torch.save(payload, path)


def test_a_checkpoint_from_a_gpu_run_loads_resumes_and_evaluates_on_cpu(tmp_path, tiny_scene_dir, monkeypatch, capsys):
    from exploregs_plugin.runs import load_run

    config = TrainerConfig(data="builtin:tiny", max_steps=20, device="cpu", run_dir=tmp_path / "run", quiet=True,
                           tensorboard=False, eval_count=1, checkpoint_every=10, save_eval_images=False,
                           schedule=ScheduleConfig(min_refine_every=10))
    Trainer(replace(config, max_steps=10)).train()
    ckpt = latest_checkpoint(tmp_path / "run")
    payload = load_checkpoint(ckpt)
    # a CUDA generator's state (seed and offset, 16 bytes) has another format than the CPU one
    payload["generator"] = torch.arange(16, dtype=torch.uint8)
    _save_as_if_from_cuda(payload, ckpt, monkeypatch)
    if NO_CUDA:  # the simulation is real: without map_location the file does not load here
        with pytest.raises(RuntimeError, match="CUDA"):
            torch.load(ckpt, weights_only=False)
    loaded = load_run(tmp_path / "run", device="cpu")
    assert loaded.step == 10 and all(p.device.type == "cpu" for p in loaded.pipeline.params.values())
    for name, value in payload["params"].items():
        assert torch.equal(loaded.pipeline.params[name].detach(), value)
    state = loaded.pipeline.optimizers["means"].state[loaded.pipeline.params["means"]]
    assert state["exp_avg"].device.type == "cpu" and state["exp_avg"].shape == payload["params"]["means"].shape
    assert not loaded.pipeline.generator_restored
    metrics = evaluate(loaded.pipeline.model, loaded.pipeline.datamanager)
    assert metrics["psnr"] > 5
    import shutil

    shutil.copytree(tmp_path / "run", tmp_path / "copy")
    resumed = Trainer.from_run(tmp_path / "run", max_steps=20, device="cpu")
    assert "saved on another device type" in capsys.readouterr().err
    assert resumed.train()["steps"] == 20
    # the reseeded stream is deterministic: resuming the same file again gives the same run
    twin = Trainer.from_run(tmp_path / "copy", max_steps=20, device="cpu")
    twin.train()
    for name, value in resumed.pipeline.params.items():
        assert torch.equal(value.detach(), twin.pipeline.params[name].detach())


def test_generator_state_of_another_format_reseeds_deterministically():
    gen = make_generator(torch.device("cpu"), 3)
    saved = gen.get_state()
    assert restore_generator(make_generator(torch.device("cpu"), 9), saved)
    foreign = torch.arange(16, dtype=torch.uint8)
    a, b = make_generator(torch.device("cpu"), 1), make_generator(torch.device("cpu"), 2)
    assert not restore_generator(a, foreign) and not restore_generator(b, foreign)
    assert torch.equal(torch.rand(4, generator=a), torch.rand(4, generator=b))
    other = make_generator(torch.device("cpu"), 1)
    restore_generator(other, torch.arange(1, 17, dtype=torch.uint8))
    assert not torch.equal(torch.rand(4, generator=other), torch.rand(4, generator=make_generator(torch.device("cpu"), 1)))


def test_to_device_moves_nested_state():
    state = {"stats": {"grad2d": torch.ones(3)}, "binoms": torch.zeros(2, 2), "scene_scale": 1.5, "list": [torch.ones(1)]}
    moved = to_device(state, torch.device("cpu"))
    assert moved["scene_scale"] == 1.5 and torch.equal(moved["stats"]["grad2d"], torch.ones(3))
    assert isinstance(moved["list"], list)


def test_machine_report_says_what_gsplat_will_and_will_not_do(monkeypatch):
    """`python -m exploregs_plugin.runtime.device`: after pip install -e ".[gpu]" on a machine without CUDA,
    one line says gsplat is installed and will not run; with CUDA but no nvcc, what is missing."""
    import importlib.metadata
    import os
    import shutil
    import subprocess
    import sys

    from exploregs_plugin.runtime.device import machine_report

    real_version = importlib.metadata.version

    def version(name):
        return "1.5.3" if name == "gsplat" else real_version(name)

    monkeypatch.setattr(importlib.metadata, "version", version)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    lines = machine_report()
    assert lines[1] == "--device auto: cpu"
    assert lines[2].startswith("gsplat 1.5.3: installed, but it will not run here: its kernels are CUDA-only")

    def missing(name):
        raise importlib.metadata.PackageNotFoundError(name)

    monkeypatch.setattr(importlib.metadata, "version", missing)
    assert machine_report()[2].startswith('gsplat: not installed; only --model.raster.backend gsplat (CUDA) needs it')

    monkeypatch.setattr(importlib.metadata, "version", version)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    monkeypatch.setattr(torch.cuda, "get_device_name", lambda i: "Some GPU")
    monkeypatch.setenv("CUDA_HOME", "/nonexistent-cuda")
    monkeypatch.setattr(shutil, "which", lambda *a, **k: None)
    lines = machine_report()
    assert "CUDA devices: Some GPU" in lines[0] and lines[1] == "--device auto: cuda"
    assert "needs nvcc for that (CUDA_HOME=/nonexistent-cuda has no bin/nvcc)" in lines[2]
    monkeypatch.undo()
    # the command itself, as CI runs it (no CUDA toolkit): exit 0, three lines
    done = subprocess.run([sys.executable, "-m", "exploregs_plugin.runtime.device"], capture_output=True, text=True,
                          env={**os.environ, "CUDA_HOME": "/nonexistent-cuda"}, timeout=120)
    assert done.returncode == 0 and len(done.stdout.strip().splitlines()) == 3, done.stderr


@pytest.mark.skipif(sys.platform == "win32", reason="POSIX file locks")
def test_gsplat_kernels_are_imported_under_a_machine_wide_lock(tmp_path, monkeypatch):
    # gsplat's first import builds its kernels after deleting its build folder: parallel processes
    # (bench jobs, ranks) must take turns, or each deletes the other's half-built files
    import fcntl
    import textwrap

    from exploregs_plugin.rasterizer.gsplat_backend import load_gsplat_kernels

    fake = tmp_path / "fake"
    (fake / "gsplat" / "cuda").mkdir(parents=True)
    (fake / "gsplat" / "__init__.py").write_text("")
    (fake / "gsplat" / "cuda" / "__init__.py").write_text("")
    (fake / "gsplat" / "cuda" / "_backend.py").write_text(textwrap.dedent("""
        import fcntl, glob, os
        lock = glob.glob(os.path.join(os.environ["TORCH_EXTENSIONS_DIR"], "*.build-lock"))[0]
        with open(lock) as other:  # another open file: blocked while the importer holds the lock
            try:
                fcntl.flock(other.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
                HELD = False
            except BlockingIOError:
                HELD = True
        _C = ("kernels", HELD)
    """))
    monkeypatch.setenv("TORCH_EXTENSIONS_DIR", str(tmp_path / "extensions"))
    for name in [m for m in sys.modules if m == "gsplat" or m.startswith("gsplat.")]:
        monkeypatch.delitem(sys.modules, name)
    monkeypatch.syspath_prepend(str(fake))
    load_gsplat_kernels.cache_clear()
    try:
        assert load_gsplat_kernels() == ("kernels", True)
        assert load_gsplat_kernels() is load_gsplat_kernels()  # once per process
        with open(next((tmp_path / "extensions").glob("*.build-lock"))) as after:
            fcntl.flock(after.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)  # released: taken at once
    finally:
        load_gsplat_kernels.cache_clear()
        for name in [m for m in sys.modules if m == "gsplat" or m.startswith("gsplat.")]:
            del sys.modules[name]
