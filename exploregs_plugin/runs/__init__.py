"""Run folders: loading a finished (or interrupted) run, and the scene (Gaussians + cameras) to
render from a run, a checkpoint or a PLY. This layer sits above the trainer and below the
commands; ``io`` below it knows file formats only."""

from .load import LoadedRun, load_run
from .scene import CameraSource, RenderableScene, cameras_from, dataset_normalization, is_ply, load_scene

__all__ = ["LoadedRun", "load_run", "CameraSource", "RenderableScene", "cameras_from", "dataset_normalization",
           "is_ply", "load_scene"]
