"""Dynamic (4D) methods end to end on the tiny built-in dynamic scene: training, strategies on the
canonical Gaussians, checkpoint and resume, evaluation per frame and region, rendering over time."""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from exploregs_plugin.method_configs import get_method
from exploregs_plugin.model import GaussianModelConfig
from exploregs_plugin.schedule import ScheduleConfig
from exploregs_plugin.engine.trainer import Trainer

STEPS = 60  # warm-up to step 12, densify at 10, 20, 30 (interval shortened for these short runs)


def dynamic_config(method: str, run_dir: Path, **overrides):
    config = get_method(method).config
    pipeline = replace(config.pipeline, datamanager=replace(config.pipeline.datamanager, data="builtin:dynamic-tiny"))
    fields = dict(max_steps=STEPS, run_dir=run_dir, quiet=True, tensorboard=False, eval_count=1,
                  checkpoint_every=20, save_eval_images=False, pipeline=pipeline,
                  schedule=ScheduleConfig(min_refine_every=10, refine_every_frac=1 / 6, refine_stop_frac=0.5))
    fields.update(overrides)
    return replace(config, **fields)


@pytest.fixture(scope="module")
def seedsplit_run(tmp_path_factory, exploregs_cache):
    """A whole run of exploregs-4d-seedsplit (random seeding, and random splitting 5 per step): read
    by the tests below, and the uninterrupted run that a run cut by Ctrl-C and resumed must equal
    (its folder and trainer are read, never changed)."""
    run_dir = tmp_path_factory.mktemp("seedsplit-4d")
    trainer = dynamic_config("exploregs-4d-seedsplit", run_dir).setup()
    metrics = trainer.train()
    return run_dir, trainer, metrics


def test_dynamic_methods_are_registered():
    for name in ("exploregs-4d-default", "exploregs-4d-split", "exploregs-4d-seedsplit"):
        config = get_method(name).config
        assert config.pipeline.datamanager.data == "builtin:dynamic"
        assert type(config.pipeline.model).__name__ == "DynamicGaussianModelConfig"
    assert get_method("exploregs-4d-split").config.pipeline.strategy.splitting.n_split == 5
    assert get_method("exploregs-4d-seedsplit").config.pipeline.strategy.splitting.n_split == 5


def test_dynamic_run_trains_deforms_and_reports_frames(seedsplit_run):
    run_dir, trainer, metrics = seedsplit_run
    model = trainer.pipeline.model
    assert bool(model.deformation.active)
    # the deformation learned something: the field's last layers left zero
    assert float(model.deformation.decoder.position[-1].weight.detach().abs().sum()) > 0
    assert metrics["num_test_images"] == 6
    frames = metrics["per_image"]
    assert [f["time"] for f in frames] == pytest.approx([0.0, 0.2, 0.4, 0.6, 0.8, 1.0])
    for key in ("psnr", "ssim", "ms_ssim", "dssim"):
        assert all(np.isfinite(f[key]) for f in frames), key
    assert metrics["dssim"] == pytest.approx((1 - metrics["ms_ssim"]) / 2)
    assert set(metrics["region_psnr"]) == {"other", "far", "occluded", "moving"}
    for key in ("region_ssim", "region_dssim"):
        assert set(metrics[key]) == set(metrics["region_psnr"])
    saved = json.loads((run_dir / "metrics.json").read_text())
    assert saved["per_image"][2]["name"] == "cam00/0002.png"
    assert trainer.op_totals.get("random_split", 0) > 0 or any(k.startswith("random") for k in trainer.op_totals)


def test_strategies_change_canonical_gaussians_field_keeps_its_state(tmp_path, exploregs_cache):
    trainer = dynamic_config("exploregs-4d-split", tmp_path / "run", max_steps=40).setup()
    pipeline = trainer.pipeline
    field_params = [p for _, p in pipeline.model.part_parameters()]
    shapes = [p.shape for p in field_params]
    counts = []
    for step in range(40):
        before = pipeline.model.num_gaussians
        pipeline.train_step(step)
        counts.append((before, pipeline.model.num_gaussians))
    assert any(after != before for before, after in counts)  # the set changed
    # the Gaussians' Adam moments follow the rows; the field's own Adam is untouched by them
    for name, opt in pipeline.optimizers.items():
        state = next(iter(opt.state.values()))
        assert state["exp_avg"].shape[0] == pipeline.model.num_gaussians, name
    assert [p.shape for p in field_params] == shapes
    field_state = pipeline.optim.shared.state
    assert all(field_state[p]["exp_avg"].shape == p.shape for p in field_params if p in field_state)
    steps = {int(field_state[p]["step"]) for p in field_params if p in field_state}
    # the field trains from the end of the warm-up (step 8 of 40) on every step
    assert steps == {40 - pipeline.model.deformation.start_step(40)}
    assert pipeline.optim.shared not in pipeline.optimizers.values()
    # its groups are part of the one optimizer set, each at its own decayed rate
    lrs = pipeline.optim.lrs()
    d = pipeline.model.config.deformation
    extent = pipeline.scene_extent
    assert set(lrs) == {"means", "scales", "quats", "opacities", "sh0", "shN", "grid", "mlp"}
    assert d.grid_lr_final * extent < lrs["grid"] < d.grid_lr * extent
    assert math.isclose(lrs["grid"] / (d.grid_lr * extent), lrs["mlp"] / (d.mlp_lr * extent), rel_tol=1e-9)


def test_checkpoint_and_resume_of_a_dynamic_run_is_bit_identical(tmp_path, seedsplit_run, ctrl_c_after_step):
    full_dir, full, _ = seedsplit_run  # the same config, trained without a cut
    cut = dynamic_config("exploregs-4d-seedsplit", tmp_path / "cut").setup()
    ctrl_c_after_step.arm(25)
    with pytest.raises(KeyboardInterrupt):
        cut.train()
    ctrl_c_after_step.disarm()
    resumed = Trainer.from_run(tmp_path / "cut")
    assert resumed.start_step == 26
    assert bool(resumed.pipeline.model.deformation.active)
    resumed.train()
    for (name, a), (_, b) in zip(full.pipeline.trained_tensors(), resumed.pipeline.trained_tensors()):
        assert torch.equal(a, b), name
    assert json.loads((full_dir / "metrics.json").read_text())["psnr"] == \
        json.loads((tmp_path / "cut" / "metrics.json").read_text())["psnr"]


def test_a_static_checkpoint_is_refused_by_a_dynamic_pipeline(tmp_path, exploregs_cache):
    trainer = dynamic_config("exploregs-4d-default", tmp_path / "run", max_steps=4).setup()
    state = trainer.pipeline.state_dict()
    static_state = {k: v for k, v in state.items() if not k.startswith("field") and k != "parts"}
    with pytest.raises(ValueError, match="holds no deformation field"):
        trainer.pipeline.load_state_dict(static_state)


def test_a_checkpoint_from_before_model_parts_loads_its_field(tmp_path, exploregs_cache):
    # checkpoints written before the deformation field became a model part hold it as "field"
    trainer = dynamic_config("exploregs-4d-default", tmp_path / "run", max_steps=4).setup()
    pipeline = trainer.pipeline
    state = pipeline.state_dict()
    assert set(state["parts"]) == {"deformation"} and "field" not in state
    old = {k: v for k, v in state.items() if k != "parts"}
    old["field"] = {k: v + 1.0 if v.is_floating_point() else v for k, v in state["parts"]["deformation"].items()}
    pipeline.load_state_dict(old)
    for key, value in pipeline.model.deformation.state_dict().items():
        assert torch.equal(value, old["field"][key]), key
    static = dynamic_config("exploregs-4d-default", tmp_path / "static", max_steps=4)
    static = replace(static, pipeline=replace(static.pipeline, model=GaussianModelConfig())).setup()
    with pytest.raises(ValueError, match="holds a deformation field"):
        static.pipeline.load_state_dict(old)


def test_eg_render_renders_the_test_camera_over_time(seedsplit_run, tmp_path):
    from exploregs_plugin.scripts.render import RenderArgs, main

    run_dir, _, _ = seedsplit_run
    out = main(RenderArgs(path=run_dir, out=tmp_path / "test", video=False, device="cpu"))
    assert len(out.frames) == 6
    frames = [np.asarray(Image.open(p), dtype=np.float64) for p in out.frames]
    # the clip moves: consecutive frames of the one camera differ
    assert min(np.abs(a - b).mean() for a, b in zip(frames, frames[1:])) > 0.01
    frozen = main(RenderArgs(path=run_dir, out=tmp_path / "frozen", video=False, device="cpu", time=0.4))
    still = [np.asarray(Image.open(p), dtype=np.float64) for p in frozen.frames]
    assert np.array_equal(still[0], still[-1])  # one camera, one time
    assert np.array_equal(still[2], frames[2])  # cam00 frame 2 is at time 0.4
    with pytest.raises(ValueError, match=r"--time must be in \[0, 1\]"):
        main(RenderArgs(path=run_dir, out=tmp_path / "bad", video=False, device="cpu", time=1.5))


def test_time_on_a_static_run_is_refused(tmp_path, tiny_scene_dir):
    from exploregs_plugin.scripts.render import RenderArgs, main
    from exploregs_plugin.engine.trainer import TrainerConfig

    TrainerConfig(data="builtin:tiny", max_steps=2, run_dir=tmp_path / "run", quiet=True, tensorboard=False,
                  eval_count=1, save_eval_images=False).setup().train()
    with pytest.raises(ValueError, match="--time is for runs of a dynamic"):
        main(RenderArgs(path=tmp_path / "run", out=tmp_path / "r", video=False, device="cpu", time=0.5))


def test_viewer_snapshot_carries_a_copy_of_the_field_and_renders_the_chosen_time(seedsplit_run):
    from exploregs_plugin.viewer.display import render_frame
    from exploregs_plugin.viewer.scene import ViewerScene
    from exploregs_plugin.viewer.snapshot import SnapshotStore

    _, trainer, _ = seedsplit_run
    pipeline = trainer.pipeline
    scene = ViewerScene.from_pipeline(pipeline)
    assert scene.deformation is not None
    store = SnapshotStore()
    store.offer(scene.params(), 1, force=True, field=scene.deformation())
    snapshot = store.latest()
    assert snapshot.field is not pipeline.model.deformation and bool(snapshot.field.active)
    camera = pipeline.datamanager.test_cameras[0]
    frames = {t: render_frame(snapshot, camera, "rgb", 0, scene.background, scene.raster_settings, t)
              for t in (0.0, 1.0)}
    assert np.abs(frames[0.0].astype(int) - frames[1.0].astype(int)).mean() > 0.01
    # the same frame eg-render makes for that time
    with torch.no_grad():
        image = pipeline.model.render(replace(camera, time=1.0), 0, scene.background)[0]
    assert np.abs((image.clamp(0, 1).numpy() * 255 + 0.5).astype(int) - frames[1.0].astype(int)).max() <= 1
    # a copy: training on does not change what the snapshot shows
    saved = {k: v.clone() for k, v in pipeline.model.deformation.state_dict().items()}
    with torch.no_grad():
        for p in pipeline.model.deformation.parameters():
            p.add_(1.0)
    again = render_frame(snapshot, camera, "rgb", 0, scene.background, scene.raster_settings, 1.0)
    pipeline.model.deformation.load_state_dict(saved)
    assert np.array_equal(again, frames[1.0])
    # a static scene has no field and no time
    assert ViewerScene.from_params(scene.params()).deformation is None


def test_eg_export_writes_the_scene_at_a_time(seedsplit_run, tmp_path):
    from exploregs_plugin.io.ply import read_ply
    from exploregs_plugin.scripts.export import ExportArgs, main

    run_dir, trainer, _ = seedsplit_run
    model = trainer.pipeline.model
    canonical = main(ExportArgs(path=run_dir, out=tmp_path / "c.ply", frame="normalized", device="cpu"))
    moment = main(ExportArgs(path=run_dir, out=tmp_path / "t.ply", frame="normalized", device="cpu", time=0.8))
    assert canonical.written == moment.written == model.num_gaussians
    with torch.no_grad():
        deformed = model.params_at(0.8)
    for name, expected in (("means", deformed["means"]), ("scales", deformed["scales"])):
        assert torch.allclose(read_ply(tmp_path / "t.ply").params[name], expected, atol=1e-5), name
    assert torch.allclose(read_ply(tmp_path / "c.ply").params["means"], model.params["means"].detach(), atol=1e-6)
    with pytest.raises(ValueError, match=r"--time must be in \[0, 1\]"):
        main(ExportArgs(path=run_dir, out=tmp_path / "x.ply", device="cpu", time=2.0))
