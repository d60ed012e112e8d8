"""``process_capture``: photos or videos in, a COLMAP dataset (``images/``, ``sparse/0``) out.

Stages, each remembered in ``OUT/process_state.json`` with the settings it ran with: ``import``
(photos upright, or the sharpest video frames, into ``images/``), ``features``, ``matching``,
``mapping``. A rerun skips the finished stages whose settings are unchanged; a changed setting
redoes its stage and those after it. The database (``OUT/database.db``) keeps the work of a stage
that was cut: a killed run loses at most the chunk it was in.
"""

from __future__ import annotations

import json
import shutil
import time
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable, Iterator, Literal

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

from ...io.atomic import atomic_write_text
from ...threads import default_threads
from ..errors import DataError
from . import sfm
from .inputs import Capture, find_capture, input_key
from .photos import import_photo, output_name
from .report import PLOT_NAME, REPORT_NAME, model_report, plot_top_view, summary_lines, write_report
from .video import extract_frames, frame_count

STATE_NAME = "process_state.json"
DATABASE_NAME = "database.db"
STAGES = ("import", "features", "matching", "mapping")
MIN_REGISTERED_SHARE = 0.5


@dataclass
class ProcessConfig:
    """How a capture is posed (eg-process's options; ``--data PHOTOS`` uses the defaults)."""

    num_frames: int = 150
    """Frames kept from the video(s), all videos together: of each window of len / num_frames
    consecutive frames the sharpest. A video with fewer frames keeps them all."""
    max_image_size: int = 1024
    """SIFT runs on images downscaled to at most this many pixels on the long side."""
    matching: Literal["auto", "exhaustive", "sequential", "spatial"] = "auto"
    """Which image pairs are matched. auto: sequential for video frames, exhaustive for up to 300
    photos, sequential above (photos in capture order); spatial needs GPS positions in the EXIF."""
    mapper: sfm.Mapper = "incremental"
    """incremental (COLMAP's) or global (GLOMAP's rotation and position averaging)."""
    camera_model: str = "SIMPLE_RADIAL"
    """COLMAP camera model estimated per camera; its distortion is removed when the dataset is read."""
    num_threads: int | None = None
    """Threads of pycolmap's stages (default: one per CPU that other processes leave idle)."""
    verbose: bool = False
    """Show pycolmap's own log lines."""

    def __post_init__(self) -> None:
        if self.num_frames < 3:
            raise DataError("--num-frames", f"must be >= 3, got {self.num_frames}")
        if self.max_image_size < 64:
            raise DataError("--max-image-size", f"must be >= 64, got {self.max_image_size}")
        if self.num_threads is not None and self.num_threads < 1:
            raise DataError("--num-threads", f"must be >= 1, got {self.num_threads}")


@dataclass
class _Layout:
    """The imported images: names in matching order, one list per video (videos only), sizes."""

    names: list[str]
    videos: list[list[str]]
    sizes: list[tuple[int, int]]


def _read_state(out: Path) -> dict:
    try:
        return json.loads((out / STATE_NAME).read_text())
    except (OSError, ValueError):
        return {}


def _write_state(out: Path, state: dict) -> None:
    atomic_write_text(out / STATE_NAME, json.dumps(state, indent=1) + "\n")


def is_posed(inputs: list[Path], out: Path) -> bool:
    """True when ``out`` holds a finished processing of ``inputs`` as they are now."""
    state = _read_state(out)
    return ((out / REPORT_NAME).is_file() and set(state.get("stages", {})) == set(STAGES)
            and state.get("input") == input_key(find_capture(inputs)))


def _inside(path: Path, folder: Path) -> bool:
    path, folder = path.resolve(), folder.resolve()
    return path == folder or folder in path.parents


def claim_output(out: Path, capture: Capture, key: list, replace_other: bool = False) -> dict:
    """The output folder's state: new or empty -> fresh; an earlier run on this input -> resume;
    an earlier run on another input -> refused, or with ``replace_other`` (the cache's own folder)
    started afresh; anything else is refused. ``out`` is never inside the input."""
    if capture.where.is_dir() and _inside(out, capture.where):
        raise DataError(out, f"is inside the input folder {capture.where}; the output goes elsewhere "
                        "(the input is never written to)")
    if out.exists() and not out.is_dir():
        raise DataError(out, "is a file; --out must be a new or empty folder")
    if out.is_dir() and any(out.iterdir()):
        state = _read_state(out)
        if not state:
            first = sorted(p.name for p in out.iterdir())[0]
            raise DataError(out, f"holds other files ({first}); --out must be a new or empty folder, "
                            "or an earlier eg-process output to resume")
        if state.get("input") != key and replace_other:
            shutil.rmtree(out)
        elif state.get("input") != key:
            raise DataError(out, f"holds the processing of another input ({len(state.get('input', []))} "
                            "files, or changed since); use another --out folder")
        else:
            return state
    out.mkdir(parents=True, exist_ok=True)
    return {"input": key, "stages": {}}


class _Stages:
    """Stage bookkeeping: which are done with today's settings, and their seconds."""

    def __init__(self, out: Path, state: dict, keys: dict[str, dict]) -> None:
        self.out, self.state, self.keys = out, state, keys
        done = state.setdefault("stages", {})
        for i, stage in enumerate(STAGES):  # a changed stage invalidates the ones after it
            if done.get(stage, {}).get("key") != keys[stage]:
                for later in STAGES[i:]:
                    done.pop(later, None)
                break

    def done(self, stage: str) -> bool:
        return stage in self.state["stages"]

    def finish(self, stage: str, seconds: float, **extra) -> None:
        self.state["stages"][stage] = {"key": self.keys[stage], "seconds": seconds, **extra}
        _write_state(self.out, self.state)

    def seconds(self) -> dict[str, float]:
        return {s: self.state["stages"][s]["seconds"] for s in STAGES if s in self.state["stages"]}


@contextmanager
def _bar(console: Console, description: str, total: int | None) -> Iterator[Callable[..., None]]:
    """One rich progress bar (counts, elapsed, ETA); yields ``update(advance=1, completed=None)``."""
    columns = (TextColumn("{task.description:<10}"), BarColumn(), MofNCompleteColumn(),
               TimeElapsedColumn(), TextColumn("ETA"), TimeRemainingColumn())
    with Progress(*columns, console=console, transient=False) as progress:
        task = progress.add_task(description, total=total)
        yield lambda advance=1, completed=None: progress.update(task, advance=advance, completed=completed)


def _import(capture: Capture, images: Path, config: ProcessConfig, console: Console) -> _Layout:
    """Photos upright, or each video's sharpest frames, into ``images`` (a fresh folder)."""
    if images.exists():
        shutil.rmtree(images)
    images.mkdir(parents=True)
    if capture.kind == "images":
        taken = {p.name for p in capture.files}
        names, sizes = [], []
        with _bar(console, "import", len(capture.files)) as advance:
            for path in capture.files:
                name = output_name(path, taken)
                sizes.append(import_photo(path, images, name))
                names.append(name)
                advance(1)
        return _Layout(names, [], sizes)
    counts = [frame_count(v) for v in capture.files]
    total = sum(counts)
    several = len(capture.files) > 1
    videos: list[list[str]] = []
    with _bar(console, "frames", total or None) as advance:
        for video, count in zip(capture.files, counts):
            # each video's share of --num-frames follows its length (equal shares when unknown)
            wanted = round(config.num_frames * count / total) if total else config.num_frames // len(counts)
            folder = images / video.stem if several else images
            folder.mkdir(exist_ok=True)
            prefix = f"{video.stem}/" if several else ""
            frames = extract_frames(video, folder, "", max(wanted, 1), on_frame=advance)
            videos.append([prefix + f for f in frames])
    names = [n for frames in videos for n in frames]
    if len(names) < 3:
        raise DataError(capture.where, f"gave {len(names)} frame(s); posing needs at least 3")
    return _Layout(names, videos, [])


def choose_matching(config: ProcessConfig, capture: Capture, n_images: int) -> tuple[str, str]:
    """(matching, why) for ``--matching auto`` or the given choice."""
    if config.matching != "auto":
        return config.matching, "--matching"
    if capture.kind == "videos":
        return "sequential", "video frames; --matching to choose"
    if n_images <= sfm.EXHAUSTIVE_MAX_IMAGES:
        return "exhaustive", f"{n_images} photos, up to {sfm.EXHAUSTIVE_MAX_IMAGES}; --matching to choose"
    return "sequential", f"{n_images} photos, over {sfm.EXHAUSTIVE_MAX_IMAGES}, in name order; --matching to choose"


def _keep_largest(models: dict, mapped: Path, out: Path) -> tuple[object, list[int]]:
    """Move the model with the most registered images to ``out/sparse/0`` and the others to
    ``out/other_models/N``; returns it and the others' registered counts."""
    import pycolmap

    order = sorted(models, key=lambda k: -models[k].num_reg_images())
    for folder in (out / "sparse", out / "other_models"):
        if folder.exists():
            shutil.rmtree(folder)
    kept = out / "sparse" / "0"
    kept.mkdir(parents=True)
    models[order[0]].write(str(kept))
    for i, k in enumerate(order[1:]):
        target = out / "other_models" / str(i)
        target.mkdir(parents=True)
        models[k].write(str(target))
    shutil.rmtree(mapped, ignore_errors=True)
    return pycolmap.Reconstruction(str(kept)), [models[k].num_reg_images() for k in order[1:]]


def process_capture(inputs: list[Path], out: Path, config: ProcessConfig | None = None,
                    console: Console | None = None, replace_other: bool = False, summary: bool = True) -> dict:
    """Pose ``inputs`` into the COLMAP dataset ``out``; returns the report (also written to
    ``out/process_report.json``). Bad input is one DataError. ``replace_other``: an ``out`` that
    holds the processing of another input (a changed capture, in the cache) is redone. ``summary``:
    print the summary (also when every stage was done before)."""
    import pycolmap

    config = config or ProcessConfig()
    console = console or Console(stderr=True)
    capture = find_capture([Path(p).expanduser() for p in inputs])
    out = Path(out).expanduser()
    state = claim_output(out, capture, input_key(capture), replace_other)
    threads = config.num_threads or default_threads()
    matching_key = {"matching": config.matching}
    stages = _Stages(out, state, {
        "import": {"num_frames": config.num_frames if capture.kind == "videos" else None},
        "features": {"max_image_size": config.max_image_size, "camera_model": config.camera_model},
        "matching": matching_key,
        "mapping": {"mapper": config.mapper},
    })
    images, database = out / "images", out / DATABASE_NAME
    if not stages.done("import"):
        start = time.perf_counter()
        layout = _import(capture, images, config, console)
        stages.finish("import", time.perf_counter() - start, layout=asdict(layout))
    layout = _Layout(**state["stages"]["import"]["layout"])
    with sfm.colmap_logs(config.verbose):
        if not stages.done("features"):
            database.unlink(missing_ok=True)
            start = time.perf_counter()
            mode = sfm.camera_mode(bool(layout.videos) and len(layout.videos) > 1, [tuple(s) for s in layout.sizes])
            with _bar(console, "features", len(layout.names)) as advance:
                sfm.extract(database, images, layout.names, mode, config.camera_model, config.max_image_size,
                            threads, advance)
            stages.finish("features", time.perf_counter() - start)
        matching, why = choose_matching(config, capture, len(layout.names))
        if not stages.done("matching"):
            console.print(f"matching: {matching} ({why})")
            start = time.perf_counter()
            if matching == "spatial":
                if sfm.pose_prior_count(database) == 0:
                    raise DataError(capture.where, "--matching spatial needs GPS positions in the photos' EXIF "
                                    "and these have none; use --matching exhaustive or sequential")
                with _bar(console, "matching", 1) as advance:
                    sfm.match_spatial(database, threads)
                    advance(1)
            else:
                if matching == "exhaustive":
                    pairs = sfm.exhaustive_pairs(layout.names)
                else:
                    pairs = sfm.video_pairs(layout.videos) if layout.videos else sfm.sequential_pairs(layout.names)
                with _bar(console, "matching", len(pairs)) as advance:
                    sfm.match_pairs(database, pairs, out / "pairs.txt", threads, advance)
                (out / "pairs.txt").unlink(missing_ok=True)
            stages.finish("matching", time.perf_counter() - start)
        if not stages.done("mapping"):
            start = time.perf_counter()
            mapped = out / ".mapping"
            shutil.rmtree(mapped, ignore_errors=True)
            with _bar(console, "mapping", len(layout.names)) as advance:
                models = sfm.map_scene(database, images, mapped, config.mapper, threads, advance)
                # the callbacks also count images of models that are dropped: show the kept one's
                advance(0, completed=max((m.num_reg_images() for m in models.values()), default=0))
            if not models:
                raise DataError(out, f"no model could be built from the {len(layout.names)} images: too few "
                                "matches; try photos with more overlap, --matching exhaustive or --mapper global")
            _, others = _keep_largest(models, mapped, out)
            stages.finish("mapping", time.perf_counter() - start, other_models=others)
    rec = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    settings = {**asdict(config), "matching": matching, "threads": threads}
    settings.pop("verbose")
    report = model_report(rec, layout.names, state["stages"]["mapping"].get("other_models", []),
                          stages.seconds(), settings)
    write_report(report, out)
    plot_top_view(rec, out / PLOT_NAME)
    for line in summary_lines(report) if summary else ():
        print(line, flush=True)
    if report["registered"] < MIN_REGISTERED_SHARE * report["images_in"]:
        raise DataError(out, f"only {report['registered']} of {report['images_in']} images registered "
                        "(under half); try photos with more overlap, --matching exhaustive or --mapper global")
    return report
