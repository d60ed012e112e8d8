"""The scene ray caster: analytic hits, normals, culling, pixel rays, visibility, textures."""

from __future__ import annotations

import numpy as np

from exploregs_plugin.data.builtin import raycast as rc
from exploregs_plugin.data.builtin.raycast import pixel_rays, trace
from exploregs_plugin.data.builtin.layouts import build_world, intrinsics, look_at
from exploregs_plugin.data.builtin.render import count_visible
from exploregs_plugin.data.builtin.textures import hash01, value_noise

GREY = rc.Material(lambda p, n: np.full_like(p, 0.5))


def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def test_sphere_box_cylinder_hits_and_normals() -> None:
    origin = np.array([0.0, 0.0, 0.0])
    dirs = _unit([[1, 0, 0], [0, 1, 0], [0, 0, 1], [0, 0, -1]])
    sphere = rc.Sphere(np.array([5.0, 0, 0]), 1.0, GREY)
    t, n = sphere.intersect(origin, dirs)
    assert t[0] == 4.0 and np.isinf(t[1:]).all()
    np.testing.assert_allclose(n[0], [-1, 0, 0])
    box = rc.Box(np.array([-1.0, 2.0, -1.0]), np.array([1.0, 3.0, 1.0]), GREY)
    t, n = box.intersect(origin, dirs)
    assert t[1] == 2.0 and np.isinf(t[[0, 2, 3]]).all()
    np.testing.assert_allclose(n[1], [0, -1, 0])
    cyl = rc.Cylinder(np.array([0.0, 0.0]), 0.5, 2.0, 3.0, GREY)
    t, n = cyl.intersect(origin, dirs)
    assert t[2] == 2.0 and np.isinf(t[[0, 1, 3]]).all()  # the bottom cap from below
    np.testing.assert_allclose(n[2], [0, 0, -1])
    side = cyl.intersect(np.array([3.0, 0.0, 2.5]), _unit([[-1, 0, 0]]))
    assert side[0][0] == 2.5
    np.testing.assert_allclose(side[1][0], [1, 0, 0])
    ground = rc.GroundPlane(-2.0, GREY)
    t, n = ground.intersect(origin, dirs)
    assert t[3] == 2.0 and np.isinf(t[:3]).all()


def test_horizon_ring_respects_its_height_profile() -> None:
    ring = rc.HorizonRing(10.0, lambda az: np.where(np.cos(az) > 0, 5.0, 1.0), GREY, max_height=5.0)
    origin = np.array([0.0, 0.0, 0.0])
    dirs = _unit([[1, 0, 0.3], [-1, 0, 0.3], [1, 0, 0.6]])  # z at the ring: 3, 3, 6
    t, _ = ring.intersect(origin, dirs)
    assert np.isclose(t[0], np.hypot(10, 3)) and np.isinf(t[1]) and np.isinf(t[2])


def test_nearest_hit_and_bounding_sphere_culling_agree_with_brute_force() -> None:
    prims = build_world("combined", 0)
    K = intrinsics(40, 30, 60.0)
    c2w = look_at(np.array([-4.0, 1.0, 1.5]), np.array([0.0, 0.0, 0.5]))
    origin, dirs, _ = pixel_rays(K, c2w, 40, 30, 1)
    hits = trace(origin, dirs, prims)
    all_t = np.stack([p.intersect(origin, dirs)[0] for p in prims])
    np.testing.assert_array_equal(hits.t, all_t.min(axis=0))
    np.testing.assert_array_equal(hits.prim, all_t.argmin(axis=0))
    kinds = {type(prims[i]).__name__ for i in np.unique(hits.prim)}
    assert {"GroundPlane", "Box", "HorizonRing", "Dome"} <= kinds  # the view sees every kind


def test_pixel_rays_centre_subsample_and_order() -> None:
    K = intrinsics(8, 6, 70.0)
    c2w = look_at(np.array([0.0, -5.0, 1.0]), np.array([0.0, 0.0, 1.0]))
    origin, dirs, z_per_t = pixel_rays(K, c2w, 8, 6, 3)
    assert dirs.shape == (8 * 6 * 9, 3)
    np.testing.assert_allclose(np.linalg.norm(dirs, axis=1), 1.0)
    w2c = np.linalg.inv(c2w)
    cam = dirs @ w2c[:3, :3].T
    pix = cam[:, :2] / cam[:, 2:] @ K[:2, :2].T + K[:2, 2]
    centre = pix.reshape(6, 8, 9, 2)[:, :, 4]  # the middle sub-sample of each pixel
    u, v = np.meshgrid(np.arange(8) + 0.5, np.arange(6) + 0.5)
    np.testing.assert_allclose(centre, np.stack([u, v], -1), atol=1e-9)
    np.testing.assert_allclose(z_per_t, cam[:, 2], atol=1e-12)


def test_count_visible_respects_occlusion() -> None:
    prims = [rc.GroundPlane(0.0, GREY), rc.Box(np.array([-0.5, -0.5, 0.0]), np.array([0.5, 0.5, 1.0]), GREY),
             rc.Dome(100.0, GREY)]
    K = intrinsics(64, 48, 60.0)
    eyes = [np.array([4.0, 0.0, 0.5]), np.array([-4.0, 0.0, 0.5])]
    c2ws = np.stack([look_at(e, np.array([0.0, 0.0, 0.5])) for e in eyes])
    w2cs = np.linalg.inv(c2ws)
    depths = []
    for c2w in c2ws:
        origin, dirs, z_per_t = pixel_rays(K, c2w, 64, 48, 1)
        depths.append((trace(origin, dirs, prims).t * z_per_t).reshape(48, 64))
    # a point on the +x face is seen only by the +x camera; one on top of the ground behind
    # each camera is outside the other's view
    points = np.array([[0.5, 0.0, 0.5], [-0.5, 0.0, 0.5], [0.0, 0.0, 1.0]])
    counts = count_visible(points, np.stack([K, K]), w2cs, np.stack(depths))
    assert counts.tolist() == [1, 1, 0]


def test_textures_are_deterministic_and_seeded() -> None:
    cells = np.array([[0, 0], [1, 0], [0, 1], [-5, 7]])
    a, b = hash01(cells, 3), hash01(cells, 3)
    np.testing.assert_array_equal(a, b)
    assert np.all((a >= 0) & (a < 1)) and len(set(a.tolist())) == 4
    assert not np.array_equal(a, hash01(cells, 4))
    pts = np.random.default_rng(0).uniform(-3, 3, (500, 3))
    noise = value_noise(pts, 2.0, 1)
    assert noise.min() >= 0 and noise.max() <= 1
    near = value_noise(pts + 1e-6, 2.0, 1)
    assert np.abs(near - noise).max() < 1e-4  # continuous
