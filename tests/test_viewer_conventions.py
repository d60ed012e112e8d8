"""viser camera <-> our Camera: checked by projecting known points."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import viser.transforms as vtf

from exploregs_plugin.cameras import Camera
from exploregs_plugin.viewer.conventions import (
    camera_forward,
    camera_to_viser,
    camera_up,
    intrinsics_from_fov,
    render_size,
    vertical_fov,
    viser_to_camera,
)


def look_at_wxyz(position: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """Camera-to-world rotation as viser documents it (OpenCV axes: x right, y down, z
    forward), built independently of the code under test."""
    z = target - position
    z = z / np.linalg.norm(z)
    x = np.cross(z, up)  # right = forward x up (for y down, z forward: x = y cross z)
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)  # down
    return vtf.SO3.from_matrix(np.stack([x, y, z], axis=1)).wxyz


def project(camera: Camera, point: np.ndarray) -> tuple[float, float, float]:
    """Pixel (u, v) and camera depth of a world point."""
    p = camera.viewmat.double() @ torch.tensor([*point, 1.0], dtype=torch.float64)
    uvw = camera.K.double() @ p[:3]
    return float(uvw[0] / uvw[2]), float(uvw[1] / uvw[2]), float(p[2])


@pytest.mark.parametrize("width,height", [(640, 480), (300, 500)])
def test_viser_camera_projects_known_points(width: int, height: int) -> None:
    position = np.array([2.0, -1.0, 3.0])
    target = np.array([0.5, 0.5, -1.0])
    up = np.array([0.0, 0.0, 1.0])
    fov = math.radians(50.0)
    camera = viser_to_camera(look_at_wxyz(position, target, up), position, fov, width, height)
    dist = float(np.linalg.norm(target - position))

    # The look-at point lands on the image centre, at its distance in front of the camera.
    u, v, z = project(camera, target)
    assert u == pytest.approx(width / 2, abs=1e-3)
    assert v == pytest.approx(height / 2, abs=1e-3)
    assert z == pytest.approx(dist, rel=1e-5)

    forward = (target - position) / dist
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    true_up = np.cross(right, forward)
    half = dist * math.tan(fov / 2)
    # A point on the upper edge of the vertical fov projects to the top row (v = 0) ...
    u, v, _ = project(camera, target + half * true_up)
    assert (u, v) == pytest.approx((width / 2, 0.0), abs=1e-3)
    # ... and one at the right edge (horizontal half-width = half * aspect) to u = W.
    u, v, _ = project(camera, target + half * (width / height) * right)
    assert (u, v) == pytest.approx((width, height / 2), abs=1e-3)
    # A point behind the camera has negative depth.
    assert project(camera, position - forward)[2] < 0


def test_round_trip_through_viser_pose() -> None:
    gen = torch.Generator().manual_seed(3)
    for _ in range(5):
        q = torch.randn(4, generator=gen, dtype=torch.float64)
        rot_c2w = vtf.SO3((q / q.norm()).numpy()).as_matrix()
        centre = torch.randn(3, generator=gen, dtype=torch.float64).numpy() * 3
        viewmat = torch.eye(4, dtype=torch.float64)
        viewmat[:3, :3] = torch.from_numpy(rot_c2w.T)
        viewmat[:3, 3] = torch.from_numpy(-rot_c2w.T @ centre)
        K = torch.tensor([[400.0, 0, 160], [0, 400.0, 120], [0, 0, 1]])
        camera = Camera(viewmat.float(), K, 320, 240, "c")
        wxyz, position = camera_to_viser(camera)
        assert np.allclose(position, centre, atol=1e-5)
        fov = vertical_fov(camera)
        assert fov == pytest.approx(2 * math.atan(120 / 400))
        back = viser_to_camera(wxyz, position, fov, 320, 240)
        assert torch.allclose(back.viewmat, camera.viewmat, atol=1e-5)
        assert torch.allclose(back.K, K, atol=1e-4)
        assert np.allclose(camera_forward(camera), rot_c2w[:, 2], atol=1e-6)
        assert np.allclose(camera_up(camera), -rot_c2w[:, 1], atol=1e-6)


def test_intrinsics_and_render_size() -> None:
    K = intrinsics_from_fov(math.pi / 2, 200, 100)
    assert float(K[1, 1]) == pytest.approx(50.0)  # (H / 2) / tan(45 deg)
    assert float(K[0, 0]) == float(K[1, 1])
    assert (float(K[0, 2]), float(K[1, 2])) == (100.0, 50.0)
    assert render_size(1600, 900, 320) == (320, 180)
    assert render_size(900, 1600, 320) == (180, 320)
    assert render_size(300, 200, 640) == (300, 200)  # never above the canvas


def test_bad_viser_cameras_are_rejected() -> None:
    with pytest.raises(ValueError, match="wxyz"):
        viser_to_camera(np.zeros(4), np.zeros(3), 1.0, 10, 10)
    with pytest.raises(ValueError, match="field of view"):
        viser_to_camera(np.array([1.0, 0, 0, 0]), np.zeros(3), 0.0, 10, 10)
    with pytest.raises(ValueError, match="image size"):
        intrinsics_from_fov(1.0, 0, 10)
    with pytest.raises(ValueError, match="finite"):
        viser_to_camera(np.array([1.0, 0, 0, 0]), np.array([np.nan, 0, 0]), 1.0, 10, 10)


def test_matches_viser_own_orbit_camera() -> None:
    """viser's CameraHandle turns (position, look_at, up) into wxyz itself; our conversion of
    that wxyz must put the look-at point at the image centre and world-up above it."""
    import viser

    class _Connection:
        def queue_message(self, message: object) -> None:
            pass

    class _Client:
        _websock_connection = _Connection()

    handle = viser.CameraHandle(_Client())  # type: ignore[arg-type]
    state = getattr(handle, "_state", None)
    if state is None or not hasattr(state, "update_timestamp"):
        pytest.skip("this viser version keeps its camera state differently")
    position, target, up = np.array([1.0, 2.0, 0.5]), np.array([-1.0, 0.0, 0.0]), np.array([0.0, 0.0, 1.0])
    state.update_timestamp = 1.0
    state.position = position
    state.up_direction = up
    handle.look_at = target  # viser computes wxyz from position, look_at and up
    camera = viser_to_camera(handle.wxyz, handle.position, math.radians(60), 400, 300)
    u, v, z = project(camera, target)
    assert (u, v) == pytest.approx((200.0, 150.0), abs=1e-3)
    assert z > 0
    _, v_up, _ = project(camera, target + 0.1 * up)
    assert v_up < 150.0  # world up appears higher in the image (smaller row)
