"""The rasterizer benchmark on a trained set: a checkpoint's Gaussians seen from one of its
training views, timed and checked against the float64 reference like the synthetic scenes."""

from __future__ import annotations

import pytest
import torch

from exploregs_plugin.bench.components.rasterizer import make_scene, run_child
from exploregs_plugin.rasterizer import RasterSettings
from exploregs_plugin.runs.load import load_run
from exploregs_plugin.engine.trainer import Trainer, TrainerConfig


@pytest.fixture(scope="module")
def trained_run(tmp_path_factory, tiny_scene_dir):
    run_dir = tmp_path_factory.mktemp("run")
    Trainer(TrainerConfig(data="builtin:tiny", max_steps=30, run_dir=run_dir, quiet=True, tensorboard=False,
                          eval_count=1, save_eval_images=False)).train()  # fmt: skip
    return run_dir


def test_a_checkpoint_scene_is_the_trained_set_from_its_training_view(trained_run):
    run = load_run(trained_run, "cpu")
    params, camera = run.pipeline.model.params, run.pipeline.datamanager.train_cameras[2]
    scene = make_scene(f"{trained_run}@2")
    assert scene.means.shape[0] == run.pipeline.model.num_gaussians > 0
    assert torch.equal(scene.means, params["means"].detach().float())
    assert torch.equal(scene.opacities, torch.sigmoid(params["opacities"].detach()).float())
    assert torch.equal(scene.scales, torch.exp(params["scales"].detach()).float())
    assert scene.sh_coeffs.shape[1] == params["sh0"].shape[1] + params["shN"].shape[1]
    assert torch.equal(scene.viewmat, camera.viewmat.float()) and (scene.width, scene.height) == (camera.width,
                                                                                                  camera.height)
    row = run_child(f"{trained_run}@2", "torch", 1, RasterSettings(workers=1))
    assert row["n"] == scene.means.shape[0] and row["pairs"] > 0
    assert row["img_max"] < 1e-4 and row["grad_rel"] < 1e-3  # against the float64 reference


def test_a_bad_scene_name_or_view_is_one_clear_error(trained_run):
    with pytest.raises(ValueError, match="no view 999"):
        make_scene(f"{trained_run}@999")
    with pytest.raises(ValueError, match="unknown scene 'nope'"):
        make_scene("nope")
