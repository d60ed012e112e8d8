"""Camera paths: quaternion maths, key ordering, interpolation through the key cameras."""

import math

import numpy as np
import pytest
import torch

from exploregs_plugin.cameras import Camera
from exploregs_plugin.io import camera_path as cp


def _look_at(eye, target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """World-to-camera [4, 4], OpenCV axes (x right, y down, z forward)."""
    eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    c2w = np.eye(4)
    c2w[:3, :3] = np.stack([x, y, z], axis=1)
    c2w[:3, 3] = eye
    return np.linalg.inv(c2w)


def _camera(viewmat: np.ndarray, name: str = "", width: int = 64, height: int = 48, f: float = 50.0) -> Camera:
    K = torch.tensor([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])
    return Camera(torch.from_numpy(viewmat).float(), K, width, height, name)


def _arc(n: int, radius: float = 4.0, span_deg: float = 120.0) -> list[Camera]:
    angles = np.radians(np.linspace(0.0, span_deg, n))
    return [_camera(_look_at([radius * math.cos(a), radius * math.sin(a), 1.0]), f"img_{i:03d}")
            for i, a in enumerate(angles)]


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def test_quaternion_round_trip_covers_every_branch():
    rng = np.random.default_rng(0)
    rotations = [_random_rotation(rng) for _ in range(50)]
    # half turns about each axis make the trace -1, forcing the non-trace branches
    rotations += [np.diag([1.0, -1.0, -1.0]), np.diag([-1.0, 1.0, -1.0]), np.diag([-1.0, -1.0, 1.0]), np.eye(3)]
    for rot in rotations:
        q = cp.rotation_to_quat(rot)
        assert abs(np.linalg.norm(q) - 1.0) < 1e-12 and q[0] >= 0.0
        np.testing.assert_allclose(cp.quat_to_rotation(q), rot, atol=1e-12)
    with pytest.raises(ValueError, match="zero quaternion"):
        cp.quat_to_rotation(np.zeros(4))


def test_slerp_endpoints_constant_speed_and_short_arc():
    rng = np.random.default_rng(1)
    q0 = cp.rotation_to_quat(_random_rotation(rng))
    q1 = cp.rotation_to_quat(_random_rotation(rng))
    np.testing.assert_allclose(cp.slerp(q0, q1, 0.0), q0, atol=1e-12)
    total = cp.rotation_angle(q0, q1)
    np.testing.assert_allclose(abs(np.dot(cp.slerp(q0, q1, 1.0), q1)), 1.0, atol=1e-12)
    for t in (0.25, 0.5, 0.8):
        q = cp.slerp(q0, q1, t)
        assert cp.rotation_angle(q0, q) == pytest.approx(t * total, abs=1e-9)
    # -q1 is the same rotation: the result must not take the long way round
    assert cp.rotation_angle(q0, cp.slerp(q0, -q1, 0.5)) == pytest.approx(0.5 * total, abs=1e-9)
    # nearly identical quaternions fall back to the normalised blend without dividing by ~0
    q = cp.slerp(q0, q0 + 1e-13, 0.5)
    assert np.isfinite(q).all() and abs(np.linalg.norm(q) - 1.0) < 1e-12


def test_catmull_rom_passes_through_ends_and_stays_on_a_line():
    p = [np.array([float(i), 0.0, 0.0]) for i in range(4)]
    assert np.array_equal(cp.catmull_rom_segment(*p, 0.0), p[1])
    np.testing.assert_allclose(cp.catmull_rom_segment(*p, 1.0), p[2], atol=1e-12)
    np.testing.assert_allclose(cp.catmull_rom_segment(*p, 0.5), [1.5, 0.0, 0.0], atol=1e-12)
    # coincident neighbours and a zero-length segment give finite points, no division by zero
    same = cp.catmull_rom_segment(p[1], p[1], p[2], p[2], 0.3)
    assert np.isfinite(same).all() and same[1] == 0.0 and 1.0 < same[0] < 2.0
    assert np.array_equal(cp.catmull_rom_segment(p[0], p[1], p[1], p[2], 0.5), p[1])


def test_path_passes_through_keys_with_orthonormal_rotations():
    keys = _arc(5)
    path = cp.interpolate_path(keys, num_frames=60)
    assert len(path.key_frames) == 5 and path.key_frames[0] == 0 and path.key_frames[-1] == len(path.cameras) - 1
    assert abs(len(path.cameras) - 60) <= 5
    for key, frame in zip(keys, path.key_frames):
        torch.testing.assert_close(path.cameras[frame].viewmat, key.viewmat, rtol=0, atol=1e-5)
        torch.testing.assert_close(path.cameras[frame].K, key.K)
    centers = []
    for cam in path.cameras:
        rot = cam.viewmat[:3, :3].double()
        torch.testing.assert_close(rot @ rot.T, torch.eye(3, dtype=torch.float64), rtol=0, atol=1e-6)
        assert torch.linalg.det(rot).item() == pytest.approx(1.0, abs=1e-6)
        assert cam.viewmat[3].tolist() == [0.0, 0.0, 0.0, 1.0]
        centers.append(cam.camera_center.double().numpy())
    centers = np.stack(centers)
    # keys lie on a circle of radius 4 at height 1, 30 degrees apart; the spline stays within a
    # fifth of the chord's sagitta 4 (1 - cos 15 deg) = 0.136 of the circle (straight lines would not)
    radius = np.linalg.norm(centers[:, :2], axis=1)
    sagitta = 4.0 * (1.0 - math.cos(math.radians(15.0)))
    assert np.abs(radius - 4.0).max() < 0.2 * sagitta and np.abs(centers[:, 2] - 1.0).max() < 1e-5
    # no jumps: consecutive frames are about evenly spaced (the arc is uniform)
    steps = np.linalg.norm(np.diff(centers, axis=0), axis=1)
    assert steps.max() < 1.5 * steps.mean() and steps.min() > 0.5 * steps.mean()


def test_turning_in_place_and_closed_loop():
    eye = [0.0, 0.0, 0.0]
    keys = [_camera(_look_at(eye, target)) for target in ([1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0])]
    path = cp.interpolate_path(keys, num_frames=21)
    centers = torch.stack([c.camera_center for c in path.cameras])
    assert torch.isfinite(centers).all() and centers.abs().max() < 1e-6
    forward = [c.viewmat[2, :3] for c in path.cameras]  # camera z axis in world coordinates
    angles = [math.degrees(math.atan2(f[1].item(), f[0].item())) for f in forward]
    assert angles[0] == pytest.approx(0.0, abs=1e-4) and angles[-1] == pytest.approx(180.0, abs=1e-4)
    assert all(b > a for a, b in zip(angles, angles[1:]))  # turns steadily one way

    ring = _arc(6, span_deg=300.0)
    loop = cp.interpolate_path(ring, num_frames=48, loop=True)
    assert len(loop.key_frames) == 6
    first, last = loop.cameras[0].camera_center, loop.cameras[-1].camera_center
    gap = torch.linalg.norm(first - last).item()
    step = torch.linalg.norm(loop.cameras[1].camera_center - first).item()
    assert gap < 2.0 * step  # the last frame leads back towards the first key


def test_intrinsics_follow_the_first_key_size():
    a = _camera(_look_at([4.0, 0.0, 1.0]), width=64, height=48, f=50.0)
    b = _camera(_look_at([0.0, 4.0, 1.0]), width=128, height=96, f=100.0)  # same field of view
    path = cp.interpolate_path([a, b], num_frames=5)
    for cam in path.cameras:
        assert (cam.width, cam.height) == (64, 48)
        torch.testing.assert_close(cam.K, a.K)
    small = cp.interpolate_path([a, b], num_frames=5, width=32, height=24)
    assert small.cameras[0].K[0, 0].item() == pytest.approx(25.0)


def test_ordering_and_key_subsampling():
    arc = _arc(9)
    shuffled = [arc[i] for i in (4, 0, 7, 2, 8, 5, 1, 6, 3)]
    order = cp.order_cameras(shuffled, "nearest")
    names = [shuffled[i].name for i in order]
    expected = [c.name for c in arc]
    assert names in (expected, expected[::-1])
    assert [shuffled[i].name for i in cp.order_cameras(shuffled, "name")] == expected
    assert cp.order_cameras(shuffled, "given") == list(range(9))
    with pytest.raises(ValueError, match="unknown camera order"):
        cp.order_cameras(shuffled, "random")
    assert cp.subsample_keys(list(range(10)), 4) == [0, 3, 6, 9]
    assert cp.subsample_keys([5, 6], 4) == [5, 6]
    with pytest.raises(ValueError, match="max_keys must be >= 2"):
        cp.subsample_keys(list(range(10)), 1)


def test_trajectory_choice_and_errors():
    train, test = _arc(7), _arc(2, radius=5.0)
    assert cp.trajectory_cameras(train, test, "test") == test
    assert cp.trajectory_cameras(train, test, "train") == train
    path = cp.trajectory_cameras(list(reversed(train)), test, "path", num_frames=30, max_keys=4, order="name")
    torch.testing.assert_close(path[0].viewmat, train[0].viewmat, rtol=0, atol=1e-5)
    torch.testing.assert_close(path[-1].viewmat, train[-1].viewmat, rtol=0, atol=1e-5)
    with pytest.raises(ValueError, match="no test cameras"):
        cp.trajectory_cameras(train, [], "test")
    with pytest.raises(ValueError, match="at least 2 key cameras"):
        cp.trajectory_cameras(train[:1], test, "path")
    with pytest.raises(ValueError, match="num_frames"):
        cp.interpolate_path(train, num_frames=3)


def test_path_stays_in_the_largest_camera_group_and_path_all_crosses_the_gap():
    arc = _arc(12, radius=4.0, span_deg=60.0)  # spacing about 0.38
    far = [_camera(_look_at((-4.0, 0.2 * k, 0.5)), f"far{k}") for k in range(3)]  # across the scene
    cameras = arc + far
    assert [len(g) for g in cp.camera_groups(cameras)] == [12, 3]
    assert cp.camera_groups(cameras)[1] == [12, 13, 14]
    centers = np.stack([c.camera_center.double().numpy() for c in cameras])
    spacing = np.median(np.sort(np.linalg.norm(centers[:, None] - centers[None], axis=-1), axis=1)[:, 1])

    def farthest(frames):
        pts = np.stack([c.camera_center.double().numpy() for c in frames])
        return np.linalg.norm(pts[:, None] - centers[None], axis=-1).min(axis=1).max()

    path = cp.trajectory_cameras(cameras, [], "path", num_frames=60)
    crossing = cp.trajectory_cameras(cameras, [], "path-all", num_frames=60)
    assert farthest(path) <= spacing  # every frame lies among the arc's cameras
    assert farthest(crossing) > 5 * spacing  # through the middle of the scene
