"""A scene to render from a run folder, a checkpoint, or a scene file plus a source of cameras.

Scene files: standard or compressed PLY, .splat, .spz (``exploregs_plugin.io.scene_files``).
Everything comes out in one frame: the normalised training frame of the run or dataset that
supplies the cameras. A scene file in the dataset's original coordinates (what ``eg-export``
writes) is mapped into that frame with the dataset's normalisation.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Literal, Mapping

import torch
from torch import Tensor

from exploregs_plugin.cameras import Camera
from exploregs_plugin.runtime.device import resolve_device
from exploregs_plugin.io.scene_files import read_scene, suffix_format
from exploregs_plugin.engine.trainer import CONFIG_NAME

PlyFrame = Literal["original", "normalized"]


@dataclass
class CameraSource:
    """Cameras (normalised frame) and what goes with them, from a run folder or a dataset.

    normalization: the dataset's ``x_norm = (x_orig + translation) * scale``, or None.
    settings: the run's rasterizer settings, or None for the defaults.
    """

    name: str
    train_cameras: list[Camera]
    test_cameras: list[Camera]
    background: Tensor | None
    normalization: Any
    settings: Any = None


@dataclass
class RenderableScene:
    """Raw Gaussian parameters (see ``exploregs_plugin.io.ply.PlyScene``) with cameras to view them."""

    params: dict[str, Tensor]
    sh_degree: int
    cameras: CameraSource
    label: str
    """Where the Gaussians came from (a checkpoint or PLY path), for messages."""
    run_dir: Path | None = None
    """The run folder, when the Gaussians come from a run."""
    step: int | None = None
    """The checkpoint's step, when the Gaussians come from a run."""
    dropped: int = 0
    """Gaussians of a PLY left out because a value was NaN or infinite."""
    model: Any = None
    """The run's model, when the Gaussians come from a run (a dynamic run deforms them over time)."""

    @property
    def is_dynamic(self) -> bool:
        """The Gaussians move: a run of a dynamic (4D) method."""
        return self.model is not None and bool(self.model.parts)

    def params_for(self, camera: Camera) -> Mapping[str, Tensor]:
        """The raw parameters to render from ``camera``: a dynamic run's, deformed to its time."""
        if self.model is None:
            return self.params
        with torch.no_grad():
            return {name: value.detach() for name, value in self.model.params_at(camera.time).items()}


def dataset_normalization(datamanager: Any) -> Any:
    """The datamanager's normalisation at full precision: the parsed scene's float64
    ``Normalization`` when it keeps one, else its ``normalization`` (translation, scale) pair."""
    parsed = getattr(datamanager, "parsed", None)
    if parsed is not None and getattr(parsed, "normalization", None) is not None:
        return parsed.normalization
    return datamanager.normalization


def model_from_params(params: dict[str, Tensor], sh_degree: int, settings: Any = None, device: str = "cpu") -> Any:
    """A ``GaussianModel`` holding imported parameters (e.g. a PLY's) on ``device``, so everything
    that takes a model (evaluation, the viewer) works on it. params: raw, as in :class:`RenderableScene`."""
    from torch import nn

    from exploregs_plugin.model.gaussians import GaussianModel, GaussianModelConfig
    from exploregs_plugin.rasterizer import RasterSettings

    config = GaussianModelConfig(sh_degree=sh_degree, raster=settings or RasterSettings())
    where = resolve_device(device)
    return GaussianModel(config, nn.ParameterDict({k: nn.Parameter(v.detach().to(where, copy=True)) for k, v in params.items()}))


def is_ply(path: Path) -> bool:
    """A ``.ply`` name (a standard or a compressed PLY)."""
    return Path(path).suffix.lower() == ".ply"


def is_scene_file(path: Path) -> bool:
    """A scene file's name: ``.ply`` (standard or compressed), ``.splat`` or ``.spz``."""
    return suffix_format(path) is not None


def scene_file_kind(path: Path) -> str:
    """How messages name a scene file: "PLY", ".splat file" or ".spz file"."""
    return "PLY" if is_ply(path) else f"{Path(path).suffix.lower()} file"


def _is_run(path: Path) -> bool:
    """A run folder, or a checkpoint file inside one."""
    path = Path(path)
    if path.is_dir():
        return (path / CONFIG_NAME).is_file()
    return path.is_file() and path.suffix == ".pt"


def cameras_from(source: str | Path, data_factor: int | None = None) -> CameraSource:
    """Cameras of a run folder (its dataset, from config.yml; no checkpoint needed), or of any
    dataset the datamanager reads (a path or ``builtin:NAME``). ``data_factor``: the dataset's
    images at 1/N size, as eg-train's ``--data-factor`` (unset: the run's factor, or 1)."""
    from exploregs_plugin.io.config_files import load_config
    from exploregs_plugin.data import DataManagerConfig
    from exploregs_plugin.io.checkpoint import resolve_run

    text = str(source)
    settings = None
    if not text.startswith("builtin:") and _is_run(Path(text)):
        path = Path(text)
        run_dir = path if path.is_dir() else resolve_run(path)[0]
        config = load_config(run_dir / CONFIG_NAME)
        dm_config = config.pipeline.datamanager
        settings = config.pipeline.model.raster
    else:
        if not text.startswith("builtin:") and not Path(text).exists():
            raise FileNotFoundError(f"--cameras-from {text}: no such run folder or dataset")
        dm_config = DataManagerConfig(data=text)
    if data_factor is not None:
        dm_config = replace(dm_config, data_factor=data_factor)
    dm = dm_config.setup()
    return CameraSource(dm.scene_name, list(dm.train_cameras), list(dm.test_cameras), dm.background,
                        dataset_normalization(dm), settings)


def load_scene(path: Path, cameras: str | Path | None = None, ply_frame: PlyFrame = "original",
               device: str = "auto", data_factor: int | None = None) -> RenderableScene:
    """Gaussians (on ``device``) and cameras from a run folder / checkpoint, or from a scene file
    (PLY, compressed PLY, .splat, .spz) with ``cameras``.

    ply_frame: whether the scene file holds the dataset's original coordinates (``original``, mapped
    into the cameras' normalised frame) or already the normalised ones (``normalized``).
    data_factor: the cameras of the dataset's images at 1/N size, as eg-train's ``--data-factor``
    (unset: the run's own factor, or 1 for a dataset).
    """
    path = Path(path)
    if is_scene_file(path):
        if cameras is None:
            raise ValueError(f"{path}: a {scene_file_kind(path)} holds no cameras; pass --cameras-from RUN_OR_DATASET "
                             f"(a run folder, a dataset folder or builtin:NAME)")
        source = cameras_from(cameras, data_factor)
        if ply_frame not in ("original", "normalized"):
            raise ValueError(f"ply_frame must be original or normalized, got {ply_frame!r}")
        scene = read_scene(path, source.normalization if ply_frame == "original" else None)
        where = resolve_device(device)
        params = {name: value.to(where) for name, value in scene.params.items()}
        return RenderableScene(params, scene.sh_degree, source, str(path), dropped=scene.dropped)
    if cameras is not None:
        raise ValueError(f"--cameras-from is for PLY input; {path} is a run, which has its own cameras")
    from exploregs_plugin.runs.load import load_run

    run = load_run(path, device)
    model, dm = run.pipeline.model, run.pipeline.datamanager
    if data_factor is None or data_factor == run.config.pipeline.datamanager.data_factor:
        source = CameraSource(dm.scene_name, list(dm.train_cameras), list(dm.test_cameras), dm.background,
                              dataset_normalization(dm), model.config.raster)
    else:  # the run's dataset at another factor, drawn as the run draws
        source = replace(cameras_from(run.run_dir, data_factor), settings=model.config.raster)
    params = {name: value.detach() for name, value in model.params.items()}
    return RenderableScene(params, model.config.sh_degree, source, str(run.checkpoint), run.run_dir, run.step,
                           model=model)
