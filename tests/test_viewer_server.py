"""The Viewer without a browser: scene content, stats, pause/resume, frames, eg-view loading."""

from __future__ import annotations

import math
import threading
from pathlib import Path

import numpy as np
import pytest
import torch

from exploregs_plugin.cameras import Camera
from exploregs_plugin.model.gaussians import rgb_to_sh0
from exploregs_plugin.viewer import ViewerConfig, ViewerScene
from exploregs_plugin.viewer.conventions import intrinsics_from_fov
from exploregs_plugin.viewer.display import render_frame
from exploregs_plugin.viewer.snapshot import Snapshot


def one_gaussian(rgb=(0.9, 0.1, 0.1), n_rest: int = 0, depth: float = 0.0) -> dict[str, torch.Tensor]:
    return {
        "means": torch.tensor([[0.0, 0.0, depth]]),
        "scales": torch.full((1, 3), math.log(0.5)),
        "quats": torch.tensor([[1.0, 0.0, 0.0, 0.0]]),
        "opacities": torch.tensor([8.0]),
        "sh0": rgb_to_sh0(torch.tensor([rgb])),
        "shN": torch.zeros(1, n_rest, 3),
    }


def camera_at(x: float, z: float = -4.0, width: int = 80, height: int = 60) -> Camera:
    """Looking along +z from (x, 0, z); world-to-camera is a pure translation."""
    viewmat = torch.eye(4)
    viewmat[0, 3], viewmat[2, 3] = -x, -z
    return Camera(viewmat, intrinsics_from_fov(math.radians(60), width, height), width, height, f"cam{x}")


@pytest.fixture()
def viewer():
    params = one_gaussian()
    scene = ViewerScene(
        params=lambda: params,
        max_sh_degree=0,
        cameras=[camera_at(0.0), camera_at(1.0), camera_at(-1.0)],
        thumbnail=lambda i: torch.full((60, 80, 3), 0.2 * i),
        points=torch.randn(500, 3, generator=torch.Generator().manual_seed(0)),
        points_rgb=torch.rand(500, 3, generator=torch.Generator().manual_seed(1)),
        extent=2.0,
    )
    v = ViewerConfig(port=0, max_thumbnails=2, max_points=100).setup(scene, training=True)
    v.test_params = params  # the live set the "trainer" changes
    yield v
    v.close()


def test_scene_content_and_stats(viewer) -> None:
    assert viewer.port > 0 and viewer.url.endswith(f":{viewer.port}")
    assert len(viewer._frustums) == 3
    # Two thumbnails, evenly spread: the first and the last camera.
    assert [h.image is not None for h in viewer._frustums] == [True, False, True]
    assert viewer._frustums[0].image.shape == (60, 80, 3)  # never upscaled past the 60-row source
    # The initial view stands at camera 0, so its frustum is hidden.
    assert [h.visible for h in viewer._frustums] == [False, True, True]
    assert viewer._points.points.shape == (100, 3)
    assert viewer._points.visible is False  # the points would cover the splats: off until asked for
    viewer.update(12, {"psnr": 20.0}, seconds=0.5)
    viewer.update(13, {"psnr": 22.0}, seconds=0.25)
    text = viewer._stats_text()
    assert "**Iteration:** 13" in text and "**Gaussians:** 1" in text
    assert "21.00 dB" in text and "0.375" in text


def test_update_copies_only_when_asked(viewer) -> None:
    copies = viewer.store.copies
    viewer.store._requested = False
    viewer.update(1, {})
    assert viewer.store.copies == copies
    viewer.store.request()
    viewer.test_params["sh0"] = rgb_to_sh0(torch.tensor([[0.1, 0.9, 0.1]]))
    viewer.update(2, {})
    assert viewer.store.copies == copies + 1 and viewer.store.latest().step == 2


def test_pause_blocks_training_until_resumed(viewer) -> None:
    viewer.wait_if_paused()  # not paused: returns at once
    viewer.set_paused(True)
    assert viewer._pause_button.label == "Resume training"
    returned = threading.Event()
    trainer = threading.Thread(target=lambda: (viewer.wait_if_paused(), returned.set()))
    trainer.start()
    assert not returned.wait(0.3)  # still blocked while paused
    viewer.set_paused(False)
    assert returned.wait(10.0)
    trainer.join()
    assert viewer._pause_button.label == "Pause training"

    viewer.set_paused(True)
    stop = threading.Event()
    stop.set()
    viewer.wait_if_paused(stop.is_set)  # Ctrl-C while paused must not hang
    viewer.close()  # closing releases a paused trainer as well
    viewer.wait_if_paused()


def test_render_frame_outputs() -> None:
    params = one_gaussian(n_rest=3)
    snap = Snapshot(params, 0, 1)
    camera = camera_at(0.0, width=40, height=30)
    rgb = render_frame(snap, camera, "rgb", sh_degree=3, background=torch.zeros(3))  # degree clipped to 1
    assert rgb.shape == (30, 40, 3) and rgb.dtype == np.uint8
    centre = rgb[15, 20].astype(int)
    assert centre[0] > 200 and centre[1] < 40 and centre[2] < 40
    assert rgb[0, 0].max() < 10  # far from the Gaussian: the black background
    alpha = render_frame(snap, camera, "alpha", 0, None)
    assert alpha[15, 20, 0] > 240 and (alpha[..., 0] == alpha[..., 2]).all()
    depth = render_frame(snap, camera, "depth", 0, None)
    assert depth[15, 20].max() > 0 and depth[0, 0].max() == 0  # coloured where covered, black elsewhere
    with pytest.raises(ValueError, match="output"):
        render_frame(snap, camera, "normals", 0, None)  # type: ignore[arg-type]


def test_config_rejects_bad_values() -> None:
    for kwargs, word in [({"max_render_share": 0.0}, "max_render_share"), ({"port": 70000}, "port"),
                         ({"output": "normals"}, "output"), ({"moving_resolution": 4}, "resolution"),
                         ({"sh_degree": 5}, "sh_degree")]:
        with pytest.raises(ValueError, match=word):
            ViewerConfig(**kwargs)


def test_eg_view_serves_a_ply(tmp_path: Path) -> None:
    from exploregs_plugin.io.ply import export_ply
    from exploregs_plugin.scripts.view import ViewArgs, main

    path = tmp_path / "one.ply"
    export_ply(path, one_gaussian(rgb=(0.2, 0.3, 0.9), n_rest=3))
    viewer = main(ViewArgs(path=path, viewer_config=ViewerConfig(port=0)))
    try:
        snap = viewer.store.latest()
        assert snap.num_gaussians == 1 and snap.params["shN"].shape == (1, 3, 3)
        assert not viewer.training and viewer.scene.max_sh_degree == 1
    finally:
        viewer.close()
    with pytest.raises(FileNotFoundError, match="no such"):
        main(ViewArgs(path=tmp_path / "missing.ply", viewer_config=ViewerConfig(port=0)))


def test_eg_view_shows_a_plys_cameras_at_the_data_factor(tmp_path: Path, tiny_scene_dir: Path) -> None:
    from exploregs_plugin.io.ply import export_ply
    from exploregs_plugin.scripts.view import ViewArgs, load_viewer_scene

    path = tmp_path / "one.ply"
    export_ply(path, one_gaussian())
    full = load_viewer_scene(ViewArgs(path=path, cameras_from=str(tiny_scene_dir)))
    half = load_viewer_scene(ViewArgs(path=path, cameras_from=str(tiny_scene_dir), data_factor=2))
    assert len(full.cameras) == len(half.cameras) > 0
    for a, b in zip(full.cameras, half.cameras):
        assert (b.width, b.height) == (a.width // 2, a.height // 2)
    with pytest.raises(ValueError, match="--data-factor is for a PLY with --cameras-from"):
        load_viewer_scene(ViewArgs(path=path, data_factor=2))
    with pytest.raises(ValueError, match="integer >= 1"):
        load_viewer_scene(ViewArgs(path=path, cameras_from=str(tiny_scene_dir), data_factor=0))


def test_viewer_on_a_training_pipeline(tiny_scene_dir: Path) -> None:
    """The trainer's hooks on a real pipeline: snapshots follow the steps, the Gaussian count
    follows densification, cameras, thumbnails and initial points come from the datamanager."""
    from exploregs_plugin.engine.trainer import TrainerConfig

    config = TrainerConfig(data="builtin:tiny", max_steps=3)
    pipeline = config.pipeline.setup(config.schedule.resolve(config.max_steps), config.seed)
    dm = pipeline.datamanager
    viewer = ViewerConfig(port=0).setup(pipeline, step=0)
    try:
        assert len(viewer._frustums) == len(dm.train_cameras)
        assert all(h.image is not None for h in viewer._frustums)  # tiny has fewer than 64 views
        assert viewer._points is not None and viewer.scene.extent == pytest.approx(dm.scene_extent)
        for step in range(2):
            viewer.wait_if_paused()
            stats = pipeline.train_step(step)
            viewer.store.request()  # as the render thread does after each frame
            viewer.update(step + 1, stats, 0.1)
        snap = viewer.store.latest()
        assert snap.step == 2 and snap.num_gaussians == pipeline.model.num_gaussians
        assert torch.equal(snap.params["means"], pipeline.params["means"].detach())
        assert "**Iteration:** 2" in viewer._stats_text()
        viewer.finish(2)
        assert "finished" in viewer._stats_text()
    finally:
        viewer.close()


def test_eg_view_stops_cleanly_on_sigterm(tmp_path: Path) -> None:
    """SIGTERM (kill, a scheduler, a container stopping) ends eg-view with one line and exit
    143, not pycolmap's crash dump."""
    import signal
    import subprocess
    import sys

    from exploregs_plugin.io.ply import export_ply

    path = tmp_path / "one.ply"
    export_ply(path, one_gaussian())
    proc = subprocess.Popen([sys.executable, "-m", "exploregs_plugin.scripts.view", str(path), "--viewer-config.port",
                             "0"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        seen = []
        while not seen or "serving" not in seen[-1]:
            line = proc.stderr.readline()
            assert line, f"eg-view ended before serving: {''.join(seen)}"
            seen.append(line)
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
    finally:
        proc.kill()
    assert proc.returncode == 128 + signal.SIGTERM, err
    assert err.strip().splitlines() == ["eg-view: stopped (SIGTERM)"], err


def test_thumbnails_close_ahead_of_the_view_are_hidden_until_they_would_not_cover_it() -> None:
    """The camera the view stands at and its close neighbours ahead would cover part of the
    picture with their thumbnails: hidden; moving back or turning round shows them again."""
    from types import SimpleNamespace

    scene = ViewerScene(params=lambda: one_gaussian(), max_sh_degree=0, extent=2.0,
                        cameras=[camera_at(0.0), camera_at(0.1), camera_at(1.0)],
                        thumbnail=lambda i: torch.full((60, 80, 3), 0.5))
    viewer = ViewerConfig(port=0).setup(scene, training=False)  # frustums 0.06 long: covering within 0.24
    try:
        # the initial view stands at camera 0: its own thumbnail and camera 1's, 0.1 aside, would cover it
        assert [h.visible for h in viewer._frustums] == [False, False, True]

        def look(position, wxyz=(1.0, 0.0, 0.0, 0.0)):
            viewer._on_camera(7, SimpleNamespace(wxyz=wxyz, position=position, fov=1.0, image_width=80,
                                                 image_height=60))
            return [h.visible for h in viewer._frustums]

        assert look((0.0, 0.0, -4.1)) == [False, False, True]  # a step back: still in the way
        assert look((0.0, 0.0, -6.0)) == [True, True, True]  # far enough back: small thumbnails
        assert look((1.0, 0.0, -4.0)) == [True, True, False]  # at camera 2
        assert look((1.0, 0.0, -4.0), wxyz=(0.0, 0.0, 1.0, 0.0)) == [True, True, True]  # turned round
        viewer._set_cameras_visible(False)
        assert look((0.0, 0.0, -6.0)) == [False, False, False]  # "Show cameras" off wins
    finally:
        viewer.close()
