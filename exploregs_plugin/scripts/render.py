"""eg-render: render a run, a checkpoint or a scene file (PLY, compressed PLY, .splat, .spz) to
PNG frames (and an MP4).

Cameras: the test views, the training views, or a smooth path through the training views.
A scene file has no cameras of its own: ``--cameras-from`` names a run folder or a dataset.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass, replace
from pathlib import Path

import torch
import tyro

from exploregs_plugin.cameras import Camera
from exploregs_plugin.data.errors import DataError
from exploregs_plugin.runtime.device import resolve_device
from exploregs_plugin.io.camera_path import CameraOrder, Trajectory, trajectory_cameras
from exploregs_plugin.io.checkpoint import check_output_folder
from exploregs_plugin.io.frames import RenderedSequence, RenderMode, render_sequence
from exploregs_plugin.io.ply import normalization_terms
from exploregs_plugin.model.gaussians import render_camera
from exploregs_plugin.rasterizer import RasterSettings, backend_line
from exploregs_plugin.runs.scene import PlyFrame, RenderableScene, load_scene
from exploregs_plugin.scripts import parse_cli, run_cli


@dataclass
class RenderArgs:
    path: tyro.conf.Positional[Path]
    """A run folder (latest checkpoint), a checkpoint file, or a scene file: a 3DGS .ply, a
    compressed .ply (.compressed.ply), .splat or .spz."""
    out: Path | None = None
    """Output folder (default: RUN/renders/TRAJECTORY-MODE-step-XXXXXXX, or STEM-render/TRAJECTORY-MODE
    beside a scene file)."""
    trajectory: Trajectory = "test"
    """Which cameras: the test views, the training views, a smooth path through the largest group of
    training cameras (path), or through all of them, across the gaps between groups (path-all)."""
    mode: RenderMode = "rgb"
    """What to draw: colour, expected depth (colour-mapped), or accumulated opacity."""
    cameras_from: str | None = None
    """For a scene file: the run folder or dataset (path or builtin:NAME) whose cameras to use."""
    ply_frame: PlyFrame = "original"
    """For a scene file: its coordinates are the dataset's original ones (as eg-export writes) or already
    normalised."""
    num_frames: int = 120
    """Path trajectory: about this many frames in all."""
    max_keys: int | None = 16
    """Path trajectory: pass through at most this many training cameras (evenly chosen along the order)."""
    order: CameraOrder = "nearest"
    """Path trajectory: order of the key cameras (nearest-neighbour chain, by name, or as listed)."""
    loop: bool = False
    """Path trajectory: close the path back to the first key camera."""
    data_factor: int | None = None
    """Render the dataset's images at 1/N size, as eg-train's --data-factor: the cameras of
    --cameras-from DATASET for a scene file; for a run (or --cameras-from RUN), instead of the factor it
    trained at (unset: the run's factor, or 1 for a dataset)."""
    sh_degree: int | None = None
    """SH degree to render with (default: the scene's)."""
    background: tuple[float, float, float] | None = None
    """Background colour in [0, 1] (default: the dataset's)."""
    fps: float = 30.0
    """Frame rate of the MP4."""
    video: bool = True
    """Also write an MP4 (H.264 through PyAV)."""
    near: float | None = None
    """Depth mode: depth shown as the first colour of the map (default: 1st percentile), dataset units."""
    far: float | None = None
    """Depth mode: depth shown as the last colour of the map (default: 99th percentile), dataset units."""
    cmap: str = "turbo"
    """Depth mode: matplotlib colour map."""
    device: str = "auto"
    """Where to compute: auto (CUDA when available, else CPU), cpu, cuda or cuda:N."""
    time: float | None = None
    """Dynamic runs: render every frame at this time in [0, 1]. Unset: test and train views at
    their own frame's time (the test camera over the clip), a path sweeping the clip from 0 to 1."""


def _default_out(args: RenderArgs, scene: RenderableScene) -> Path:
    leaf = f"{args.trajectory}-{args.mode}"
    if scene.run_dir is None:  # a scene file: beside it
        return args.path.with_name(f"{args.path.stem}-render") / leaf
    # one folder of images per run: the end-of-training panels and these frames (runs from
    # before this had a separate RUN/render/, which stays where it is)
    return scene.run_dir / "renders" / f"{leaf}-step-{scene.step:07d}"


def frame_times(scene: RenderableScene, cameras: list[Camera], trajectory: str, time: float | None) -> list[Camera]:
    """The cameras with the times to render them at: ``time`` for all; unset, a path through a
    dynamic scene sweeps the clip (0 to 1) and dataset views keep their frame's time."""
    if time is not None:
        if not scene.is_dynamic:
            raise ValueError(f"--time is for runs of a dynamic (4D) method; {scene.label} is static")
        if not 0.0 <= time <= 1.0:
            raise ValueError(f"--time must be in [0, 1], got {time}")
        return [replace(camera, time=time) for camera in cameras]
    if scene.is_dynamic and trajectory.startswith("path"):
        last = max(len(cameras) - 1, 1)
        return [replace(camera, time=i / last) for i, camera in enumerate(cameras)]
    return cameras


def _progress(i: int, n: int) -> None:
    # one updating line on a terminal; in a log, a line every tenth of the way
    if sys.stdout.isatty():
        print(f"  frame {i + 1}/{n}", end="\r" if i + 1 < n else "\n", flush=True)
    elif (i + 1) % max(1, n // 10) == 0 or i + 1 == n:
        print(f"  frame {i + 1}/{n}", flush=True)


def main(args: RenderArgs) -> RenderedSequence:
    if args.data_factor is not None and args.data_factor < 1:
        raise DataError("--data-factor", f"must be an integer >= 1, got {args.data_factor}")
    if args.out is not None:
        check_output_folder("--out", args.out)
    if args.background is not None and not all(0.0 <= c <= 1.0 for c in args.background):
        raise ValueError(f"--background must be three values in [0, 1], got {args.background}")
    scene = load_scene(args.path, args.cameras_from, args.ply_frame, args.device, args.data_factor)
    source = scene.cameras
    print(backend_line(source.settings or RasterSettings(), resolve_device(args.device)))
    if scene.dropped:
        print(f"{scene.label}: left out {scene.dropped} Gaussians with non-finite values")
    cameras = frame_times(scene, trajectory_cameras(source.train_cameras, source.test_cameras, args.trajectory,
                                                    args.num_frames, args.max_keys, args.order, args.loop),
                          args.trajectory, args.time)
    sh_degree = scene.sh_degree if args.sh_degree is None else args.sh_degree
    if not 0 <= sh_degree <= scene.sh_degree:
        raise ValueError(f"--sh-degree must be in 0..{scene.sh_degree} for this scene, got {sh_degree}")
    background = torch.tensor(args.background, dtype=torch.float32) if args.background else source.background
    # Depths are rendered in the normalised frame; report them in the dataset's units.
    _, scale = normalization_terms(source.normalization)
    out = args.out or _default_out(args, scene)
    print(f"rendering {len(cameras)} {args.trajectory} frames ({args.mode}) of {scene.label} -> {out}")
    def render(camera: Camera) -> tuple:
        return render_camera(scene.params_for(camera), camera, sh_degree=sh_degree, background=background,
                             settings=source.settings)

    result = render_sequence(
        render,
        cameras, out, mode=args.mode, fps=args.fps, video=args.video, near=args.near, far=args.far,
        depth_scale=1.0 / scale, cmap=args.cmap,
        on_frame=_progress,
    )
    print(f"wrote {len(result.frames)} PNG frames to {out}")
    if result.near is not None:
        print(f"depth colour range (dataset units): near {result.near:.6g}  far {result.far:.6g}")
    if result.video is not None:
        print(f"video: {result.video}")
    elif result.video_note:
        print(result.video_note)
    return result


def entrypoint() -> None:
    description = "Render an ExploreGS run or a scene file (PLY, .splat, .spz) to frames and video."
    run_cli("eg-render", main, parse_cli("eg-render", RenderArgs, description))


if __name__ == "__main__":
    entrypoint()
