"""Conversions between viser's camera description and our ``Camera``.

viser describes a camera by ``wxyz`` and ``position`` with ``P_world = R(wxyz) p_camera +
position``, camera axes OpenCV-style (x right, y down, z forward: the frustum docs and
``CameraHandle.wxyz`` say so), and a *vertical* field of view ``fov`` in radians. Our
``Camera`` holds the inverse map, world-to-camera ``viewmat = [[R^T, -R^T position], [0, 1]]``,
and pinhole intrinsics; for a vertical fov over an image of height H the focal length is
``f = (H / 2) / tan(fov / 2)`` (square pixels), principal point at the image centre
``(W / 2, H / 2)`` (pixel centres at +0.5, so the centre lies between the middle pixels).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from exploregs_plugin.cameras import Camera

_MIN_FOV = 1e-4  # radians; a zero or negative fov has no pinhole model
_MAX_FOV = math.pi - 1e-4


def intrinsics_from_fov(fov_y: float, width: int, height: int) -> torch.Tensor:
    """K [3, 3] of a centred pinhole with vertical field of view ``fov_y`` (radians)."""
    if not _MIN_FOV <= fov_y <= _MAX_FOV:
        raise ValueError(f"vertical field of view must be in (0, pi) radians, got {fov_y}")
    if width < 1 or height < 1:
        raise ValueError(f"image size must be positive, got {width}x{height}")
    focal = 0.5 * height / math.tan(0.5 * fov_y)
    return torch.tensor(
        [[focal, 0.0, 0.5 * width], [0.0, focal, 0.5 * height], [0.0, 0.0, 1.0]], dtype=torch.float32
    )


def viser_to_camera(
    wxyz: np.ndarray, position: np.ndarray, fov_y: float, width: int, height: int, name: str = "viewer"
) -> Camera:
    """Our ``Camera`` for a viser camera pose (camera-to-world ``wxyz``, ``position``)."""
    wxyz = np.asarray(wxyz, dtype=np.float64)
    position = np.asarray(position, dtype=np.float64)
    norm = float(np.linalg.norm(wxyz))
    if wxyz.shape != (4,) or position.shape != (3,) or not math.isfinite(norm) or norm < 1e-12:
        raise ValueError(f"viser camera needs a non-zero wxyz [4] and a position [3], got {wxyz} and {position}")
    if not np.all(np.isfinite(position)):
        raise ValueError(f"viser camera position must be finite, got {position}")
    import viser.transforms as vtf  # viser loads where a viewer or a page uses it, not for --help

    rot_c2w = vtf.SO3(wxyz / norm).as_matrix()  # [3, 3]
    viewmat = np.eye(4)
    viewmat[:3, :3] = rot_c2w.T
    viewmat[:3, 3] = -rot_c2w.T @ position
    K = intrinsics_from_fov(fov_y, width, height)
    return Camera(torch.from_numpy(viewmat).float(), K, int(width), int(height), name)


def vertical_fov(camera: Camera) -> float:
    """Vertical field of view in radians: 2 atan(H / (2 fy))."""
    fy = float(camera.K[1, 1])
    if not fy > 0.0:
        raise ValueError(f"camera {camera.name!r} has a non-positive focal length fy={fy}")
    return 2.0 * math.atan(0.5 * camera.height / fy)


def camera_to_viser(camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """viser pose of our camera: (``wxyz`` [4], ``position`` [3]), camera-to-world."""
    viewmat = camera.viewmat.detach().double().cpu().numpy()
    rot_w2c = viewmat[:3, :3]
    # Project onto the nearest rotation so that slightly non-orthonormal poses (float32
    # round-off, parser output) still give a valid quaternion.
    u, _, vt = np.linalg.svd(rot_w2c)
    rot_w2c = u @ vt
    if np.linalg.det(rot_w2c) < 0.0:
        raise ValueError(f"camera {camera.name!r} has a reflection in its viewmat, not a rotation")
    rot_c2w = rot_w2c.T
    position = -rot_c2w @ viewmat[:3, 3]
    import viser.transforms as vtf

    return vtf.SO3.from_matrix(rot_c2w).wxyz, position


def camera_up(camera: Camera) -> np.ndarray:
    """World direction of the camera's up (-y in OpenCV axes) [3]."""
    return -camera.viewmat[1, :3].detach().double().cpu().numpy()


def camera_forward(camera: Camera) -> np.ndarray:
    """World direction the camera looks along (+z in OpenCV axes) [3]."""
    return camera.viewmat[2, :3].detach().double().cpu().numpy()


def render_size(width: int, height: int, longest_side: int) -> tuple[int, int]:
    """Size of a render with the aspect of a ``width`` x ``height`` canvas whose longest side is
    ``longest_side`` (never larger than the canvas itself)."""
    if width < 1 or height < 1:
        raise ValueError(f"canvas size must be positive, got {width}x{height}")
    scale = min(1.0, longest_side / max(width, height))
    return max(1, int(round(width * scale))), max(1, int(round(height * scale)))
