"""Training speed with and without the viewer's render thread running beside it.

    python -m exploregs_plugin.bench.components.viewer --data builtin:default --steps 60 --shares 0.2 1.0

A simulated browser looks through the first training camera on a ``canvas`` sized canvas
(camera at rest, so every frame is a sharp one); the render thread renders from snapshots
exactly as the viewer does (JPEG encoding and the websocket are left out). Runs alternate
(no viewer, share 1, share 2, ... per repeat, after one uncounted warm-up run) so that
machine load drifts hit all alike.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import torch
import tyro

from exploregs_plugin.engine.trainer import TrainerConfig
from exploregs_plugin.viewer.conventions import camera_to_viser, vertical_fov
from exploregs_plugin.viewer.display import render_frame
from exploregs_plugin.viewer.render_loop import BrowserCamera, RenderLoop, ViewSettings
from exploregs_plugin.viewer.snapshot import SnapshotStore


@dataclass
class BenchArgs:
    data: str = "builtin:default"
    """Dataset to train on (as eg-train --data)."""
    steps: int = 60
    """Training steps per run."""
    shares: tuple[float, ...] = (0.2, 1.0)
    """Render CPU shares to measure (each against a run without the viewer)."""
    repeats: int = 2
    """Alternating repeats of every configuration."""
    canvas: tuple[int, int] = (1024, 640)
    """Size of the simulated browser canvas (width height)."""
    resolution: int = 640
    """Longest side of the rendered frames."""
    seed: int = 0
    """Training seed."""


def run_once(args: BenchArgs, share: float | None) -> dict[str, Any]:
    """Train ``args.steps`` steps; with ``share`` set, the render thread runs alongside."""
    config = TrainerConfig(data=args.data, max_steps=args.steps, seed=args.seed)
    torch.set_flush_denormal(config.flush_denormal)  # as the Trainer does
    pipeline = config.pipeline.setup(config.schedule.resolve(config.max_steps), config.seed)
    store = SnapshotStore()
    store.offer(pipeline.params, 0, force=True)
    loop = None
    if share is not None:
        dm, raster = pipeline.datamanager, pipeline.model.config.raster

        def render(snapshot, camera, settings):  # the viewer's render (Viewer._render)
            return render_frame(snapshot, camera, settings.output, settings.sh_degree, dm.background, raster)

        settings = ViewSettings("rgb", pipeline.model.config.sh_degree, args.resolution, args.resolution, 0.0, share)
        loop = RenderLoop(store, render, lambda frame: None, settings, throttled=lambda: True)
        first = dm.train_cameras[0]
        wxyz, position = camera_to_viser(first)
        loop.set_camera(0, BrowserCamera(wxyz, position, vertical_fov(first), *args.canvas))
        loop.start()
    start = time.perf_counter()
    for step in range(args.steps):
        pipeline.train_step(step)
        if store.offer(pipeline.params, step + 1) and loop is not None:
            loop.wake()
    wall = time.perf_counter() - start
    if loop is None:
        return {"share": None, "seconds_per_step": wall / args.steps, "frames": 0, "render_share": 0.0, "copies": 0}
    loop.stop()
    return {"share": share, "seconds_per_step": wall / args.steps, "frames": loop.duty.frames,
            "render_share": loop.duty.busy_seconds / wall, "copies": store.copies - 1}


def main(args: BenchArgs) -> list[dict[str, Any]]:
    if args.steps < 1 or args.repeats < 1:
        raise ValueError("steps and repeats must be >= 1")
    configs: list[float | None] = [None, *args.shares]
    run_once(args, None)  # warm-up (first-call costs), not counted
    runs = [run_once(args, share) for _ in range(args.repeats) for share in configs]
    print(f"{args.data}, {args.steps} steps x {args.repeats} repeats, canvas {args.canvas[0]}x{args.canvas[1]}, "
          f"frames at {args.resolution} px")
    print(f"{'viewer':>12} {'s/step':>8} {'slowdown':>9} {'frames':>7} {'render busy':>12} {'copies':>7}")
    base = sum(r["seconds_per_step"] for r in runs if r["share"] is None) / args.repeats
    for share in configs:
        mine = [r for r in runs if r["share"] == share]
        sps = sum(r["seconds_per_step"] for r in mine) / len(mine)
        label = "off" if share is None else f"share {share:g}"
        print(f"{label:>12} {sps:8.3f} {sps / base:8.2f}x {sum(r['frames'] for r in mine) / len(mine):7.1f} "
              f"{sum(r['render_share'] for r in mine) / len(mine):11.1%} "
              f"{sum(r['copies'] for r in mine) / len(mine):7.1f}")
    return runs


if __name__ == "__main__":
    main(tyro.cli(BenchArgs, description="Measure how the live viewer's rendering slows training."))
