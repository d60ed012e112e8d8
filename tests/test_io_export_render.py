"""eg-export / eg-render on a tiny trained run: frames, re-imported renders, CLI errors."""

import sys

import numpy as np
import pytest
import torch
from PIL import Image
from plyfile import PlyData

from exploregs_plugin.data import DataManagerConfig, ParseOptions, parse_dataset
from exploregs_plugin.io import ply as P
from exploregs_plugin.io.frames import to_uint8
from exploregs_plugin.runs.scene import dataset_normalization, load_scene
from exploregs_plugin.model.gaussians import render_params
from exploregs_plugin.runs import load_run
from exploregs_plugin.scripts import export as export_script
from exploregs_plugin.scripts import render as render_script
from exploregs_plugin.engine.trainer import TrainerConfig


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("run")
    TrainerConfig(data="builtin:tiny", max_steps=20, run_dir=run_dir, quiet=True, tensorboard=False,
                  eval_count=1, save_eval_images=False).setup().train()
    return load_run(run_dir)


def _render(params, camera, run):
    model, dm = run.pipeline.model, run.pipeline.datamanager
    with torch.no_grad():
        return render_params(params, camera, model.config.sh_degree, dm.background, settings=model.config.raster)


def test_export_lands_in_the_original_dataset_frame(run, tmp_path):
    model, dm = run.pipeline.model, run.pipeline.datamanager
    norm = dataset_normalization(dm)
    raw = parse_dataset("builtin:tiny", ParseOptions(), normalize=False)  # the dataset's own coordinates
    assert raw.points is not None
    known = raw.points[:3]  # [3, 3] in the dataset's units
    params = {k: v.detach().clone() for k, v in model.params.items()}
    params["means"][:3] = torch.from_numpy(norm.apply_points(known)).float()
    ply_path = tmp_path / "scene.ply"
    P.export_ply(ply_path, params, norm)
    vertex = PlyData.read(str(ply_path))["vertex"]
    xyz = np.stack([vertex["x"], vertex["y"], vertex["z"]], axis=1).astype(np.float64)
    # exact up to float32 rounding: of the normalised point (half an ulp of |x + t| s, which is
    # |x + t| in file units) and of the written coordinate (half an ulp of |x|)
    eps = float(np.finfo(np.float32).eps)
    assert (np.abs(xyz[:3] - known) <= eps * (np.abs(known + norm.translation) + np.abs(known))).all()
    expected = norm.invert_points(params["means"].double().numpy())  # computed once in float64
    assert (np.abs(xyz - expected) <= 0.5 * eps * np.abs(expected)).all()
    sigma = np.exp(np.stack([vertex[f"scale_{i}"] for i in range(3)], axis=1).astype(np.float64))
    np.testing.assert_allclose(sigma, np.exp(params["scales"].double().numpy()) / norm.scale, rtol=1e-5)


def test_cli_export_reimported_renders_identically(run, tmp_path):
    model, dm = run.pipeline.model, run.pipeline.datamanager
    original = export_script.main(export_script.ExportArgs(run.checkpoint, out=tmp_path / "orig.ply"))
    normalized = export_script.main(export_script.ExportArgs(run.run_dir, out=tmp_path / "norm.ply",
                                                             frame="normalized"))
    assert original.written == normalized.written == model.num_gaussians and original.dropped == 0
    header = PlyData.read(str(original.path)).comments
    assert any("frame original" in line for line in header)

    same_frame = P.read_ply(normalized.path)
    mapped_back = P.read_ply(original.path, dataset_normalization(dm))
    for camera in dm.test_cameras + dm.train_cameras[:2]:
        reference = _render(model.params, camera, run)
        # the normalised-frame file holds the very same float32 values: bit-identical images
        for ref, got in zip(reference[:3], _render(same_frame.params, camera, run)[:3]):
            assert torch.equal(ref, got)
        # the original-frame file went through x / s - t and back: equal up to float32 rounding
        image, alpha, depth, _ = _render(mapped_back.params, camera, run)
        torch.testing.assert_close(image, reference[0], rtol=0, atol=1e-5)
        torch.testing.assert_close(alpha, reference[1], rtol=0, atol=1e-5)
        torch.testing.assert_close(depth, reference[2], rtol=1e-5, atol=1e-5)


def test_cli_render_run_and_ply_give_the_same_frames(run, tmp_path):
    model, dm = run.pipeline.model, run.pipeline.datamanager
    frames = render_script.main(render_script.RenderArgs(run.run_dir, out=tmp_path / "run", video=False))
    assert len(frames.frames) == len(dm.test_cameras) >= 1
    for path, camera in zip(frames.frames, dm.test_cameras):
        expected = to_uint8(_render(model.params, camera, run)[0].numpy())
        assert np.array_equal(np.array(Image.open(path)), expected)

    ply_path = export_script.main(export_script.ExportArgs(run.run_dir, out=tmp_path / "s.ply")).path
    from_ply = render_script.main(render_script.RenderArgs(ply_path, out=tmp_path / "ply", video=False,
                                                           cameras_from=str(run.run_dir)))
    assert len(from_ply.frames) == len(frames.frames)
    for a, b in zip(frames.frames, from_ply.frames):
        diff = np.abs(np.array(Image.open(a)).astype(int) - np.array(Image.open(b)).astype(int))
        assert diff.max() <= 1  # float32 rounding of the coordinates can flip the last 8-bit level

    # the dataset itself also supplies the cameras (same builtin scene, same normalisation)
    scene = load_scene(ply_path, "builtin:tiny")
    assert len(scene.cameras.test_cameras) == len(dm.test_cameras)
    torch.testing.assert_close(scene.cameras.test_cameras[0].viewmat, dm.test_cameras[0].viewmat)
    torch.testing.assert_close(scene.params["means"], model.params["means"].detach(), rtol=0, atol=1e-5)


def test_cli_render_path_depth_and_alpha(run, tmp_path, capsys):
    out = render_script.main(render_script.RenderArgs(run.run_dir, out=tmp_path / "depth", trajectory="path",
                                                      mode="depth", num_frames=6, max_keys=3, video=False,
                                                      data_factor=2))
    printed = capsys.readouterr().out
    assert "near" in printed and f"{out.near:.6g}" in printed and f"{out.far:.6g}" in printed
    assert 0.0 < out.near < out.far
    first = np.array(Image.open(out.frames[0]))
    half = DataManagerConfig(data="builtin:tiny", data_factor=2).setup().train_cameras[0]  # the run's at factor 2
    assert half.width < run.pipeline.datamanager.train_cameras[0].width
    assert first.shape == (half.height, half.width, 3) and len(out.frames) >= 6
    alpha = render_script.main(render_script.RenderArgs(run.run_dir, out=tmp_path / "alpha", trajectory="train",
                                                        mode="alpha", video=False))
    grey = np.array(Image.open(alpha.frames[0]))
    camera = run.pipeline.datamanager.train_cameras[0]
    assert np.array_equal(grey[..., 1], to_uint8(_render(run.pipeline.model.params, camera, run)[1][..., 0].numpy()))


def test_render_takes_the_data_factor_of_the_dataset_it_reads_cameras_from(run, tmp_path, monkeypatch, capsys):
    # eg-render scene.ply --cameras-from DATASET --data-factor N: the dataset's views at 1/N size,
    # as eg-train --data DATASET --data-factor N trains on them
    ply_path = tmp_path / "s.ply"
    export_script.main(export_script.ExportArgs(run.run_dir, out=ply_path))
    monkeypatch.setattr(sys, "argv", ["eg-render", str(ply_path), "--cameras-from", "builtin:tiny", "--data-factor",
                                      "2", "--out", str(tmp_path / "half"), "--no-video"])
    render_script.entrypoint()
    half = DataManagerConfig(data="builtin:tiny", data_factor=2).setup().test_cameras
    frames = sorted((tmp_path / "half").glob("frame_*.png"))
    assert len(frames) == len(half)
    assert np.array(Image.open(frames[0])).shape == (half[0].height, half[0].width, 3)
    assert half[0].width < run.pipeline.datamanager.test_cameras[0].width
    capsys.readouterr()
    monkeypatch.setattr(sys, "argv", ["eg-render", str(ply_path), "--cameras-from", "builtin:tiny", "--data-factor", "0"])
    with pytest.raises(SystemExit) as exit_info:
        render_script.entrypoint()
    assert exit_info.value.code == 2
    assert capsys.readouterr().err.strip().splitlines() == ["eg-render: error: --data-factor: must be an integer >= 1, got 0"]


def test_cli_errors_are_clear(run, tmp_path, monkeypatch, capsys):
    ply_path = tmp_path / "s.ply"
    P.export_ply(ply_path, run.pipeline.model.params)
    cases = [
        ([str(ply_path)], "a PLY holds no cameras; pass --cameras-from"),
        ([str(ply_path), "--cameras-from", str(tmp_path / "nowhere")], "no such run folder or dataset"),
        ([str(run.run_dir), "--cameras-from", "builtin:tiny"], "--cameras-from is for PLY input"),
        ([str(run.run_dir), "--sh-degree", "7"], "--sh-degree must be in 0..3"),
        ([str(tmp_path / "missing")], "neither a run folder nor a checkpoint"),
    ]
    for argv, message in cases:
        monkeypatch.setattr(sys, "argv", ["eg-render", *argv])
        with pytest.raises(SystemExit) as exit_info:
            render_script.entrypoint()
        assert exit_info.value.code == 2
        assert message in capsys.readouterr().err
    (tmp_path / "bad.ply").write_text("ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n1\n")
    monkeypatch.setattr(sys, "argv", ["eg-render", str(tmp_path / "bad.ply"), "--cameras-from", str(run.run_dir)])
    with pytest.raises(SystemExit):
        render_script.entrypoint()
    assert "bad.ply: vertex element lacks y, z, f_dc_0" in capsys.readouterr().err
    monkeypatch.setattr(sys, "argv", ["eg-export", str(tmp_path / "missing")])
    with pytest.raises(SystemExit) as exit_info:
        export_script.entrypoint()
    assert exit_info.value.code == 2 and "eg-export: error" in capsys.readouterr().err


def test_imported_ply_evaluates_like_the_run(run, tmp_path):
    from exploregs_plugin.evaluation.metrics import evaluate
    from exploregs_plugin.runs.scene import model_from_params

    model, dm = run.pipeline.model, run.pipeline.datamanager
    path = export_script.main(export_script.ExportArgs(run.run_dir, out=tmp_path / "s.ply")).path
    scene = load_scene(path, str(run.run_dir))
    imported = model_from_params(scene.params, scene.sh_degree, scene.cameras.settings)
    assert imported.num_gaussians == model.num_gaussians and imported.config.sh_degree == model.config.sh_degree
    ours, theirs = evaluate(imported, dm), evaluate(model, dm)
    assert ours["psnr"] == pytest.approx(theirs["psnr"], abs=1e-3)
    assert ours["ssim"] == pytest.approx(theirs["ssim"], abs=1e-5)


def test_eg_eval_on_an_exported_ply_matches_the_run(run, tmp_path):
    from exploregs_plugin.scripts import eval as eval_script

    path = export_script.main(export_script.ExportArgs(run.run_dir, out=tmp_path / "scene.ply")).path
    of_run = eval_script.main(eval_script.EvalArgs(run.run_dir, out=tmp_path / "run-eval", save_images=False))
    of_ply = eval_script.main(eval_script.EvalArgs(path, data="builtin:tiny", save_images=False))
    assert of_ply["num_gaussians"] == of_run["num_gaussians"]
    assert of_ply["psnr"] == pytest.approx(of_run["psnr"], abs=1e-3)  # original-frame float32 round trip
    assert of_ply["ssim"] == pytest.approx(of_run["ssim"], abs=1e-5)
    assert (tmp_path / "scene-eval" / "metrics.json").is_file()
    with pytest.raises(ValueError, match="pass --data"):
        eval_script.main(eval_script.EvalArgs(path))


def test_eg_eval_says_how_many_ply_rows_it_left_out(run, tmp_path, capsys):
    from exploregs_plugin.scripts import eval as eval_script

    path = export_script.main(export_script.ExportArgs(run.run_dir, out=tmp_path / "scene.ply")).path
    ply = PlyData.read(str(path), mmap=False)
    vertices = ply["vertex"].data
    total = len(vertices)
    vertices["x"][:2] = np.nan
    vertices["opacity"][5] = np.inf
    ply.write(str(path))
    capsys.readouterr()
    metrics = eval_script.main(eval_script.EvalArgs(path, data="builtin:tiny", save_images=False))
    err = capsys.readouterr().err
    assert f"{path}: left out 3 of {total} Gaussians (PLY rows) with NaN or inf values; scoring the other " \
           f"{total - 3}" in err
    assert metrics["num_gaussians"] == total - 3 and metrics["dropped_nonfinite"] == 3


def test_eg_render_of_a_run_writes_into_the_runs_one_renders_folder(tmp_path):
    """A run has one folder of images, renders/: the end-of-training panels and eg-render's frames."""
    from types import SimpleNamespace

    scene = SimpleNamespace(run_dir=tmp_path / "run", step=1500)
    out = render_script._default_out(render_script.RenderArgs(tmp_path / "run"), scene)
    assert out == tmp_path / "run" / "renders" / "test-rgb-step-0001500"
    ply = render_script._default_out(render_script.RenderArgs(tmp_path / "s.ply", trajectory="path", mode="depth"),
                                     SimpleNamespace(run_dir=None, step=0))
    assert ply == tmp_path / "s-render" / "path-depth"
