"""eg-view: serve a finished run, a checkpoint or a scene file in the browser until Ctrl-C.

    eg-view outputs/SCENE/METHOD/STAMP                 # latest checkpoint of a run
    eg-view outputs/.../checkpoints/step-0003000.pt    # one checkpoint
    eg-view scene.ply [--cameras-from RUN_OR_DATASET]  # a PLY (ours or another tool's)
    eg-view scene.spz                                  # also .splat and .compressed.ply
    eg-view RUN --viewer-config.port 8081 --viewer-config.rest-resolution 1024
"""

from __future__ import annotations

import signal
import sys
from dataclasses import dataclass, field
from pathlib import Path

import tyro

from exploregs_plugin.runtime.device import resolve_device
from exploregs_plugin.io.checkpoint import CheckpointError
from exploregs_plugin.rasterizer import RasterSettings, backend_line
from exploregs_plugin.runs.scene import PlyFrame, is_scene_file, load_scene, scene_file_kind
from exploregs_plugin.scripts import parse_cli
from exploregs_plugin.runtime.threads import apply_threads
from exploregs_plugin.viewer import Viewer, ViewerConfig, ViewerScene


@dataclass
class ViewArgs:
    path: tyro.conf.Positional[Path]
    """A run folder (uses its latest checkpoint), a checkpoint file, or a scene file: a 3DGS
    .ply, a compressed .ply (.compressed.ply), .splat or .spz."""
    cameras_from: str | None = None
    """Scene file only: a run folder, dataset folder or builtin:NAME whose training cameras are
    shown (the file is mapped into their normalised frame, see --ply-frame). Unset: no cameras."""
    ply_frame: PlyFrame = "original"
    """Scene file with --cameras-from: the file holds the dataset's original coordinates (what
    eg-export writes) or already the normalised training frame."""
    data_factor: int | None = None
    """Scene file with --cameras-from DATASET: its images at 1/N size, as eg-train's --data-factor (the
    cameras' thumbnails; unset: 1). A run shows the images at the factor it trained at."""
    device: str = "auto"
    """Where to compute: auto (CUDA when available, else CPU), cpu, cuda or cuda:N."""
    viewer_config: ViewerConfig = field(default_factory=ViewerConfig)
    """The viewer's settings (port, resolutions, output, ...): --viewer-config.*, as for eg-train."""


def load_viewer_scene(args: ViewArgs) -> ViewerScene:
    """What to show for ``args.path``: a run's pipeline (cameras with thumbnails, initial
    points) or a scene file's Gaussians (with the cameras of --cameras-from, if given)."""
    path = Path(args.path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such run folder, checkpoint or PLY file")
    if args.data_factor is not None and args.data_factor < 1:
        raise ValueError(f"--data-factor must be an integer >= 1, got {args.data_factor}")
    if args.data_factor is not None and (not is_scene_file(path) or args.cameras_from is None):
        kind = scene_file_kind(path) if is_scene_file(path) else "PLY"
        raise ValueError(f"--data-factor is for a {kind} with --cameras-from; {path} "
                         + ("has no cameras without it" if is_scene_file(path) else
                            "is a run, shown at the factor it trained at"))
    if is_scene_file(path):
        if args.cameras_from is None:
            from exploregs_plugin.io.scene_files import read_scene

            scene_file = read_scene(path)
            if scene_file.dropped:
                print(f"{path}: left out {scene_file.dropped} Gaussians with non-finite values", file=sys.stderr)
            where = resolve_device(args.device)
            return ViewerScene.from_params({k: v.to(where) for k, v in scene_file.params.items()}, name=path.stem)
        loaded = load_scene(path, args.cameras_from, args.ply_frame, args.device, args.data_factor)
        scene = ViewerScene.from_params(loaded.params, loaded.cameras.train_cameras, loaded.cameras.background,
                                        name=f"{path.stem} ({loaded.cameras.name})")
        scene.raster_settings = loaded.cameras.settings
        return scene
    if args.cameras_from is not None:
        raise ValueError(f"--cameras-from is for PLY input; {path} is a run, which has its own cameras")
    from exploregs_plugin.runs import load_run

    run = load_run(path, args.device)
    return ViewerScene.from_pipeline(run.pipeline, step=run.step)


def main(args: ViewArgs) -> Viewer:
    """Start the viewer (it serves from background threads) and return it."""
    scene = load_viewer_scene(args)
    print(backend_line(scene.raster_settings or RasterSettings(), resolve_device(args.device)))
    return args.viewer_config.setup(scene, training=False)


class _Terminated(Exception):
    """SIGTERM arrived (from kill, a scheduler or a container stopping)."""


def _on_sigterm(signum: int, frame: object) -> None:
    signal.signal(signal.SIGTERM, signal.SIG_DFL)  # a second SIGTERM ends the process at once
    raise _Terminated


def entrypoint() -> None:
    # pycolmap installs a failure-signal handler that prints a crash dump on SIGTERM: stop with
    # one line instead (exit 143 = 128 + SIGTERM); Ctrl-C stops the same way with exit 0
    signal.signal(signal.SIGTERM, _on_sigterm)
    apply_threads()  # one thread per CPU this process may use, as in every command
    args = parse_cli("eg-view", ViewArgs,
                     "Serve a trained ExploreGS scene (run, checkpoint, or PLY, .splat or .spz file) in the browser.")
    viewer = None
    try:
        try:
            viewer = main(args)
        except (ValueError, FileNotFoundError, CheckpointError) as err:
            print(f"eg-view: error: {err}", file=sys.stderr)
            raise SystemExit(2) from err
        print("eg-view: serving; press Ctrl-C to stop", file=sys.stderr)
        viewer.serve_forever()
    except _Terminated:
        print("eg-view: stopped (SIGTERM)", file=sys.stderr)
        raise SystemExit(128 + signal.SIGTERM) from None
    except KeyboardInterrupt:  # Ctrl-C while loading; while serving, serve_forever returns
        print("eg-view: interrupted", file=sys.stderr)
        raise SystemExit(130) from None
    finally:
        if viewer is not None:
            viewer.close()


if __name__ == "__main__":
    entrypoint()
