"""Seeds that land in empty space are pruned in a short run; seeds outside every view are counted.

The scene is already explained: the training targets are the initial model's own renders and
ADC growth is off, so the seeds are the only change to a perfect fit. A seed whose 3-sigma ball
is nearer than every surface under its 3-sigma footprint, in every view that sees it, can only
add error, so it fades; seed probation (``RandomSeeding.prune_opa``) removes it once it is below the
probation threshold. Seeds that no view sees get no gradient: they are counted in
``seeds_unseen`` while they live. Refinement runs every 20 steps, seeding every 100 and the
opacity reset at step 200 (3DGS's 100 / 3000 shortened for a 400-step run).
"""

from __future__ import annotations

from dataclasses import replace

import torch

from exploregs_plugin.method_configs import get_method
from exploregs_plugin.strategies import SeedingStrategy
from exploregs_plugin.strategies.seeding import SEED_FLAG, SEED_SEEN, RandomSeeding

STEPS = 400
N_SEED = 40
SEED_EVERY = 100
RESET_EVERY = 200
RUN_SEED = 1
"""Trainer seed: places two of the tracked seeds in empty space and several outside every view.
Without probation (``prune_opa=0`` of the operator, normal pruning only) both empty-space seeds of this run
survive at opacities above the 0.005 threshold."""
TRACKED = (100, 200)
"""Seeding steps whose batches are followed: the first fades from its start opacity, the second
is born at the reset (explore runs before it) and must climb; both have a full judging period."""
TAG = "test_seed_index"  # per-row statistic: 1 + index in the seed batch (0 = not a seed); ops carry it


def footprint_class(means, sigma, cameras, surfaces, k_sigma=3.0):
    """Where each seed lies against the training views.

    means: [S, 3]; sigma: [S] largest std; surfaces: per view [H, W] depth of the rendered
    surface (inf where the render is mostly background). Returns (in_view [S]: its centre
    projects into some view; free [S]: its 3-sigma ball is nearer than every surface under its
    3-sigma footprint in every view that sees it; unseen [S]: the footprint misses every view).
    """
    s = means.shape[0]
    in_view = torch.zeros(s, dtype=torch.bool)
    free = torch.ones(s, dtype=torch.bool)
    unseen = torch.ones(s, dtype=torch.bool)
    for cam, surface in zip(cameras, surfaces):
        cam_pts = means @ cam.viewmat[:3, :3].T + cam.viewmat[:3, 3]
        z = cam_pts[:, 2]
        z_safe = z.clamp_min(1e-6)
        u = cam.K[0, 0] * cam_pts[:, 0] / z_safe + cam.K[0, 2]
        v = cam.K[1, 1] * cam_pts[:, 1] / z_safe + cam.K[1, 2]
        radius = k_sigma * sigma * cam.K[0, 0] / z_safe
        for j in range(s):
            if float(z[j]) <= 0.01:
                continue
            x0, x1 = max(int(u[j] - radius[j]), 0), min(int(u[j] + radius[j]) + 1, cam.width)
            y0, y1 = max(int(v[j] - radius[j]), 0), min(int(v[j] + radius[j]) + 1, cam.height)
            if x0 >= x1 or y0 >= y1:
                continue
            unseen[j] = False
            in_view[j] |= bool(0 <= u[j] < cam.width and 0 <= v[j] < cam.height)
            if not float(z[j] + k_sigma * sigma[j]) < float(surface[y0:y1, x0:x1].min()):
                free[j] = False
    return in_view, free, unseen


def test_empty_space_seeds_are_pruned_and_unseen_seeds_counted(tmp_path, tiny_scene_dir, monkeypatch):
    config = get_method("exploregs-seed").config
    strategy = SeedingStrategy(seeding=RandomSeeding(n_seed=N_SEED, every=SEED_EVERY), refine_every=20, refine_start_iter=19,
                               refine_stop_iter=STEPS, reset_every=RESET_EVERY, grow_grad2d=1e9)
    config = replace(config, data="builtin:tiny", max_steps=STEPS, run_dir=tmp_path, quiet=True,
                     tensorboard=False, seed=RUN_SEED,
                     pipeline=replace(config.pipeline, strategy=strategy))
    pipeline = config.setup().pipeline
    dm = pipeline.datamanager
    assert strategy.seeding.prune_opa > strategy.prune_opa  # probation is on by default

    cameras, targets, surfaces = [], {}, []
    with torch.no_grad():
        for i in range(len(dm.train_cameras)):
            camera, _, _ = dm.train_item(i)
            image, alpha, depth, _ = pipeline.model.render(camera, 0, dm.background)
            cameras.append(camera)
            targets[i] = image
            a, d = alpha[..., 0], depth[..., 0]
            surfaces.append(torch.where(a > 0.5, d / a.clamp_min(1e-6), torch.full_like(d, float("inf"))))
    train_item = dm.train_item

    def explained_target(index, device=None, downscale=1):  # no coarse-to-fine levels in this run
        camera, _, extras = train_item(index, device, downscale)
        return camera, targets[index] if device is None else targets[index].to(device), extras

    monkeypatch.setattr(dm, "train_item", explained_target)

    stats = pipeline.strategy_state["stats"]
    born_means, born_sigma = [], []
    seeds_pruned = 0
    for step in range(STEPS):
        out = pipeline.train_step(step)
        seeds_pruned += out["counts"].get("seeds_pruned", 0)
        if step in TRACKED:
            # Tag this batch (rows just appended: seed flag set, no tag yet); ops carry the tag
            # through clone, split and prune.
            assert out["counts"]["seeded"] == N_SEED
            if TAG not in stats:
                stats[TAG] = torch.zeros_like(stats[SEED_FLAG])
            new = (stats[SEED_FLAG] > 0) & (stats[TAG] == 0)
            first = len(born_means)
            stats[TAG][new] = torch.arange(first + 1, first + N_SEED + 1, dtype=stats[TAG].dtype)
            born_means += list(pipeline.params["means"].detach()[new].clone())
            born_sigma += list(pipeline.params["scales"].detach()[new].exp().max(dim=-1).values)
        if step == RESET_EVERY - 1:
            # Before the first reset the first batch's seeds outside every view are alive, have
            # never been seen, and are reported.
            _, _, unseen = footprint_class(torch.stack(born_means), torch.stack(born_sigma), cameras,
                                           surfaces, k_sigma=4.0)
            outside = (torch.nonzero(unseen).flatten() + 1).tolist()
            assert len(outside) >= 2, "the fixed seed must put some seeds outside every view"
            for k in outside:
                rows = stats[TAG] == k
                assert bool(rows.any()) and bool((stats[SEED_SEEN][rows] == 0).all())
            assert pipeline.exploration_summary()["seeds_unseen"] >= len(outside)

    in_view, free, _ = footprint_class(torch.stack(born_means), torch.stack(born_sigma), cameras, surfaces)
    empty = (torch.nonzero(in_view & free).flatten() + 1).tolist()
    assert len(empty) >= 2, "the fixed seed must put some seeds in empty space"
    alive = set(stats[TAG][stats[TAG] > 0].long().tolist())
    survivors = [k for k in empty if k in alive]
    assert survivors == [], f"seeds in empty space survived: {survivors} of {empty}"
    assert seeds_pruned >= len(empty)
    # The explained scene is intact: the seeds left no visible error behind.
    with torch.no_grad():
        errors = [float(((pipeline.model.render(c, 0, dm.background)[0] - targets[i]) ** 2).mean())
                  for i, c in enumerate(cameras)]
    assert max(errors) < 1e-3, errors
