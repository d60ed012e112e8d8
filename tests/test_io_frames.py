"""Frame writing: depth colour mapping and range, alpha/rgb frames, video writer fallback."""

import importlib.util
import math
from functools import partial

import matplotlib
import numpy as np
import pytest
import torch
from PIL import Image

from exploregs_plugin.cameras import Camera
from exploregs_plugin.io import frames as F
from exploregs_plugin.model.gaussians import render_camera


def test_depth_range_uses_covered_pixels_and_never_collapses():
    depth = np.linspace(1.0, 100.0, 100).reshape(10, 10)
    alpha = np.ones_like(depth)
    alpha[0] = 0.0  # the first row (depths 1..10) is not covered: ignored
    near, far = F.depth_range([depth], [alpha])
    covered = depth[1:].ravel()
    assert near == pytest.approx(np.percentile(covered, 1.0)) and far == pytest.approx(np.percentile(covered, 99.0))
    assert near > 10.0
    flat_near, flat_far = F.depth_range([np.full((4, 4), 2.0)], [np.ones((4, 4))])
    assert flat_near < 2.0 < flat_far
    assert F.depth_range([np.ones((2, 2))], [np.zeros((2, 2))]) == (0.0, 1.0)


def test_colorize_depth_maps_near_and_far_to_the_ends_of_the_colour_map():
    depth = np.array([[1.0, 3.0, 5.0, 9.0, np.nan]])
    alpha = np.array([[1.0, 1.0, 1.0, 1.0, 1.0]])
    alpha_low = alpha.copy()
    alpha_low[0, 2] = 0.2
    out = F.colorize_depth(depth, alpha_low, near=1.0, far=5.0, cmap="viridis")
    cmap = matplotlib.colormaps["viridis"]
    assert out.dtype == np.uint8 and out.shape == (1, 5, 3)
    assert out[0, 0].tolist() == F.to_uint8(np.array(cmap(0.0)[:3])).tolist()
    assert out[0, 1].tolist() == F.to_uint8(np.array(cmap(0.5)[:3])).tolist()
    assert out[0, 2].tolist() == [0, 0, 0]  # barely covered pixel: black
    assert out[0, 3].tolist() == F.to_uint8(np.array(cmap(1.0)[:3])).tolist()  # beyond far: clipped
    assert out[0, 4].tolist() == out[0, 3].tolist()  # NaN depth shows as far
    with pytest.raises(ValueError, match="far > near"):
        F.colorize_depth(depth, alpha, near=2.0, far=2.0)
    with pytest.raises(ValueError, match="unknown colour map 'nope'"):
        F.colorize_depth(depth, alpha, near=1.0, far=2.0, cmap="nope")


def _scene():
    """Two Gaussians in front of a camera at the origin looking down +z."""
    params = {
        "means": torch.tensor([[-0.3, 0.0, 2.0], [0.3, 0.0, 4.0]]),
        "scales": torch.log(torch.full((2, 3), 0.25)),
        "quats": torch.tensor([[1.0, 0.0, 0.0, 0.0]] * 2),
        "opacities": torch.tensor([4.0, 4.0]),
        "sh0": torch.tensor([[[1.0, -1.0, -1.0]], [[-1.0, -1.0, 1.0]]]),
        "shN": torch.zeros(2, 0, 3),
    }
    K = torch.tensor([[40.0, 0.0, 16.0], [0.0, 40.0, 12.0], [0.0, 0.0, 1.0]])
    cameras = [Camera(torch.eye(4), K, 32, 24, "a"), Camera(torch.eye(4), K, 32, 24, "b")]
    return params, cameras


def test_render_sequence_writes_rgb_alpha_and_depth_frames(tmp_path):
    params, cameras = _scene()
    render = partial(render_camera, params, sh_degree=0, background=None)
    image, alpha, depth = render_camera(params, cameras[0], 0, None)
    assert image.shape == (24, 32, 3) and alpha.shape == depth.shape == (24, 32)

    rgb = F.render_sequence(render, cameras, tmp_path / "rgb", mode="rgb", video=False)
    assert [p.name for p in rgb.frames] == ["frame_00000.png", "frame_00001.png"] and rgb.video is None
    assert np.array_equal(np.array(Image.open(rgb.frames[0])), F.to_uint8(image))
    assert rgb.near is None

    al = F.render_sequence(render, cameras, tmp_path / "alpha", mode="alpha", video=False)
    grey = np.array(Image.open(al.frames[1]))
    assert np.array_equal(grey[..., 0], F.to_uint8(alpha)) and np.array_equal(grey[..., 0], grey[..., 2])

    dp = F.render_sequence(render, cameras, tmp_path / "depth", mode="depth", video=False,
                           depth_scale=10.0, cmap="viridis")
    covered = np.concatenate([depth[alpha >= 0.5] * 10.0] * 2)  # both cameras see the same
    assert dp.near == pytest.approx(np.percentile(covered, 1.0), rel=1e-6)
    assert dp.far == pytest.approx(np.percentile(covered, 99.0), rel=1e-6)
    assert 20.0 <= dp.near < dp.far <= 40.0  # the Gaussians sit at depth 2 and 4, times depth_scale
    expected = F.colorize_depth(depth * 10.0, alpha, dp.near, dp.far, "viridis")
    assert np.array_equal(np.array(Image.open(dp.frames[0])), expected)

    fixed = F.render_sequence(render, cameras[:1], tmp_path / "depth", mode="depth", video=False,
                              near=0.0, far=50.0)
    assert (fixed.near, fixed.far) == (0.0, 50.0)
    # re-rendering fewer frames into the same folder leaves no stale frame behind
    assert sorted(p.name for p in (tmp_path / "depth").iterdir()) == ["frame_00000.png"]
    with pytest.raises(ValueError, match="far > near"):
        F.render_sequence(render, cameras, tmp_path / "bad", mode="depth", near=3.0, far=1.0)
    with pytest.raises(ValueError, match="unknown render mode"):
        F.render_sequence(render, cameras, tmp_path / "bad", mode="normals")
    with pytest.raises(ValueError, match="no cameras"):
        F.render_sequence(render, [], tmp_path / "bad")


def test_without_a_video_writer_frames_are_still_written(tmp_path, monkeypatch):
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "av" else real(name, *a))
    assert "PyAV is not installed" in F.video_writer_status()
    params, cameras = _scene()
    render = partial(render_camera, params, sh_degree=0, background=None)
    out = F.render_sequence(render, cameras, tmp_path)
    assert out.video is None and "PNG frames only" in out.video_note and len(out.frames) == 2
    assert not list(tmp_path.glob("*.mp4"))


def test_mp4_through_pyav(tmp_path):
    import av

    params, cameras = _scene()
    render = partial(render_camera, params, sh_degree=0, background=None)
    cameras = [Camera(c.viewmat, c.K, 31, 24, c.name) for c in cameras] * 3  # odd width: padded for H.264
    out = F.render_sequence(render, cameras, tmp_path, fps=12)
    assert out.video == tmp_path / "rgb.mp4" and out.video_note is None
    with av.open(str(out.video)) as container:
        stream = container.streams.video[0]
        assert stream.codec_context.name == "h264" and math.isclose(float(stream.average_rate), 12.0)
        frames = [frame.to_ndarray(format="rgb24") for frame in container.decode(stream)]
    assert len(frames) == 6 and frames[0].shape == (24, 32, 3)
    # lossy, but the red Gaussian stays red and the blue one blue
    first = np.array(Image.open(out.frames[0])).astype(int)
    assert np.abs(frames[0][:, :31].astype(int) - first).mean() < 12.0
