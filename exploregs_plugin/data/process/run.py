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
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Literal

from rich.console import Console

from ...io.atomic import atomic_write_text
from ...runtime.threads import default_threads
from ..errors import DataError
from . import checks, retrieval, sfm
from .config import ProcessConfig
from .inputs import STATE_NAME, Capture, find_capture, input_key, relative_name
from .photos import import_photo, output_name
from .progress import StageLog, stage_progress
from .report import (
    PLOT_NAME,
    REPORT_NAME,
    model_report,
    plot_top_view,
    shown_names,
    summary_lines,
    write_report,
)
from .video import extract_frames, frame_count

DATABASE_NAME = "database.db"
STAGES = ("import", "features", "matching", "mapping")
MIN_REGISTERED_SHARE = 0.5
RETRIEVAL_FROM = 60
"""From this many photos on, --matching auto retrieves pairs instead of matching all of them. Each
photo gets its 20 most similar and its next 10, about 30 n / 2 pairs against n (n - 1) / 2, so
below about 40 photos retrieval matches nearly every pair anyway and adds the vocabulary's cost;
at beer's 71 it matched 1,229 pairs instead of 2,485 in 10.6 s instead of 18.8 s, with the same
registration (docs/data.md)."""
SECOND_ROUND_TOP_K = 2 * retrieval.TOP_K
"""Retrieval's second round matches a weak photo with this many of its most similar photos."""


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


def _import(capture: Capture, images: Path, config: ProcessConfig, console: Console, log: StageLog) -> _Layout:
    """Photos upright, or each video's sharpest frames, into ``images`` (a fresh folder)."""
    if images.exists():
        shutil.rmtree(images)
    images.mkdir(parents=True)
    if capture.kind == "images":
        # a photo in a subfolder keeps its path below the input folder: unique, and stable
        taken = {relative_name(p, capture.where) for p in capture.files}
        names, sizes = [], []
        with stage_progress(console, log, "import", len(capture.files), "photos") as advance:
            for path in capture.files:
                name = output_name(relative_name(path, capture.where), taken)
                sizes.append(import_photo(path, images, name))
                names.append(name)
                advance(1)
        return _Layout(names, [], sizes)
    counts = [frame_count(v) for v in capture.files]
    total = sum(counts)
    several = len(capture.files) > 1
    videos: list[list[str]] = []
    with stage_progress(console, log, "frames", total or None, "frames read") as advance:
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
    if n_images < RETRIEVAL_FROM:
        return "exhaustive", f"{n_images} photos, under {RETRIEVAL_FROM}; --matching to choose"
    return "retrieval", f"{n_images} photos, {RETRIEVAL_FROM} or more; --matching to choose"


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


def _match(matching: str, layout: _Layout, database: Path, out: Path, capture: Capture, threads: int,
           console: Console, log: StageLog) -> dict:
    """Match the pairs ``matching`` chooses; returns what the stage records (pairs, order)."""
    if matching == "spatial":
        if sfm.pose_prior_count(database) == 0:
            raise DataError(capture.where, "--matching spatial needs GPS positions in the photos' EXIF "
                            "and these have none; use --matching exhaustive, retrieval or sequential")
        with stage_progress(console, log, "matching", 1, "calls") as advance:
            sfm.match_spatial(database, threads)
            advance(1)
        return {}
    extra: dict = {}
    if matching == "exhaustive":
        pairs = sfm.exhaustive_pairs(layout.names)
    elif matching == "retrieval":
        log.line("retrieval: a vocabulary from the capture's own features")
        pairs, _, ordered = retrieval.plan_pairs(database, layout.names, sequential_overlap=sfm.SEQUENTIAL_OVERLAP)
        extra["ordered"] = bool(ordered)
        log.line(f"retrieval: {len(pairs)} pairs of {len(layout.names) * (len(layout.names) - 1) // 2}"
                 f" (names {'are' if ordered else 'are not'} the capture order)")
    else:
        pairs = sfm.video_pairs(layout.videos) if layout.videos else sfm.sequential_pairs(layout.names)
    with stage_progress(console, log, "matching", len(pairs), "pairs") as advance:
        sfm.match_pairs(database, pairs, out / "pairs.txt", threads, advance)
    (out / "pairs.txt").unlink(missing_ok=True)
    return {"pairs": len(pairs), **extra}


def _second_round(layout: _Layout, database: Path, out: Path, rec, threads: int, console: Console,
                  log: StageLog) -> int:
    """Retrieval's second round: the photos left unregistered, or registered on few points, are
    matched with more of their most similar photos. Returns the pairs it matched (0: none)."""
    registered = {im.name: im.num_points3D for im in rec.images.values() if im.has_pose}
    floor = checks.weak_floor(list(registered.values()))
    weak = [n for n in layout.names if registered.get(n, 0) < floor]
    if not weak:
        return 0
    # the first round's plan again (it is deterministic): its pairs are done, found or not
    first, sim, _ = retrieval.plan_pairs(database, layout.names, sequential_overlap=sfm.SEQUENTIAL_OVERLAP)
    done = {frozenset(p) for p in first} | sfm.matched_pairs(database)
    pairs = retrieval.more_pairs(layout.names, sim, weak, SECOND_ROUND_TOP_K, done)
    if pairs:
        log.line(f"retrieval, second round: {len(weak)} photos unregistered or weak, {len(pairs)} more pairs")
        with stage_progress(console, log, "matching+", len(pairs), "pairs") as advance:
            sfm.match_pairs(database, pairs, out / "pairs.txt", threads, advance)
        (out / "pairs.txt").unlink(missing_ok=True)
    return len(pairs)


def _map(layout: _Layout, database: Path, images: Path, out: Path, mapper: str, config: ProcessConfig,
         threads: int, console: Console, log: StageLog, folder: str) -> dict:
    """Map ``database`` with ``mapper`` into ``out/folder``; the models found (empty: none)."""
    mapped = out / folder
    shutil.rmtree(mapped, ignore_errors=True)
    # the incremental mapper reports each image it registers; the global one nothing until done
    total = len(layout.names) if mapper == "incremental" else None
    with stage_progress(console, log, f"mapping ({mapper})", total, "registered") as advance:
        models = sfm.map_scene(database, images, mapped, mapper, threads, config.deterministic, advance)
        # the callbacks also count images of models that are dropped: show the kept one's
        advance(0, completed=max((m.num_reg_images() for m in models.values()), default=0))
    shutil.rmtree(mapped, ignore_errors=True)  # the models are in memory; _keep_largest writes one
    return models


def _best(models: dict):
    """The model with the most registered images (None: no model)."""
    return max(models.values(), key=lambda m: m.num_reg_images()) if models else None


class _Attempt:
    """One mapping of the capture: how it was made, its models and what the checks found."""

    def __init__(self, how: str, mapper: str, models: dict, found: checks.ModelChecks | None) -> None:
        self.how, self.mapper, self.models, self.found = how, mapper, models, found

    def score(self) -> tuple[int, int]:
        """Fewer suspect images first, then more images registered that are not suspect."""
        if not self.models or self.found is None:
            return (10 ** 9, 0)
        return (len(self.found.suspect), -(_best(self.models).num_reg_images() - len(self.found.suspect)))


def _mapping(layout: _Layout, database: Path, images: Path, out: Path, matching: str, ordered: bool | None,
             config: ProcessConfig, threads: int, console: Console, log: StageLog) -> dict:
    """Map, check the model, remedy a failed one; writes ``sparse/0`` (and ``other_models/``) and
    returns what the stage records: the mapper and pairs kept, every attempt's checks, the images
    left out.

    The remedies, in order, until a model passes: (1) for a capture with an order, map again from
    the matches between neighbours only (``sfm.window_database``); (2) the other mapper on all the
    matches. The attempt with the fewest suspect images is kept, and with ``remedy`` its suspect
    images are left out of the dataset."""
    def attempt(how: str, mapper: str, db: Path) -> _Attempt:
        models = _map(layout, db, images, out, mapper, config, threads, console, log, ".mapping")
        # every attempt is checked against all the matches, whichever it was mapped from
        found = checks.check_model(_best(models), layout.names, database, ordered) if models else None
        for line in checks.check_lines(found, _best(models).num_reg_images()) if found else ["no model"]:
            log.line(f"{how}, {mapper}: {line}")
        return _Attempt(how, mapper, models, found)

    other = "global" if config.mapper == "incremental" else "incremental"
    first = attempt(f"{matching} pairs", config.mapper, database)
    if matching == "retrieval" and first.models and _second_round(layout, database, out, _best(first.models),
                                                                  threads, console, log):
        first = attempt(f"{matching} pairs, second round", config.mapper, database)
    attempts = [first]
    if config.remedy and first.found is not None and not first.found.passed:
        log.line(f"note: the model fails its checks ({len(first.found.suspect)} suspect images: "
                 f"{shown_names(first.found.suspect, 4)}); trying to remedy it", show=True)
        window_db = out / "database-window.db"
        if first.found.ordered and sfm.window_database(database, window_db, layout.names):
            attempts.append(attempt(f"neighbour pairs (window {sfm.SEQUENTIAL_OVERLAP})", config.mapper, window_db))
        window_db.unlink(missing_ok=True)
        if attempts[-1].found is None or not attempts[-1].found.passed:
            slow = " (slow on a large capture: over 25 minutes for 252 photos here)" if other == "incremental" else ""
            log.line(f"note: mapping again with the {other} mapper{slow}", show=True)
            attempts.append(attempt(f"{matching} pairs", other, database))
    kept = min(attempts, key=_Attempt.score)  # the first of equals: the plain attempt
    if not kept.models:
        raise DataError(out, f"no model could be built from the {len(layout.names)} images: too few "
                        f"matches; try photos with more overlap, --matching exhaustive or --mapper {other}")
    rec, others = _keep_largest(kept.models, out / ".mapping", out)
    left_out: list[str] = []
    came_back: list[str] = []
    if config.remedy and not kept.found.passed:
        checks.leave_out(rec, kept.found.suspect)
        came_back, left_out = _second_chance(rec, kept.found, database, layout.names, threads,
                                             config.deterministic, log)
        rec.write(str(out / "sparse" / "0"))
    if len(attempts) > 1:
        log.line(f"note: kept the model from {kept.how} with the {kept.mapper} mapper "
                 f"({len(kept.found.suspect)} suspect images)", show=True)
    return {"mapper": kept.mapper, "pairs_kept": kept.how, "checks": kept.found.to_dict(), "left_out": left_out,
            "came_back": came_back,
            "attempts": [{"how": a.how, "mapper": a.mapper,
                          "registered": _best(a.models).num_reg_images() if a.models else 0,
                          "suspect": len(a.found.suspect) if a.found else None} for a in attempts],
            "other_models": others}


def _second_chance(rec, found: checks.ModelChecks, database: Path, names: list[str], threads: int,
                   deterministic: bool, log: StageLog) -> tuple[list[str], list[str]]:
    """The suspect images of the kept model, left out of ``rec``, registered again into it (the model
    that is right without them) and checked again: ``(came back, still left out)``. An image
    comes back when it registers and the checks of the model with it find it, and every image
    kept before, not suspect; otherwise the images that registered are left out again."""
    suspect = found.suspect
    registered = sfm.register_into(database, rec, suspect, threads, deterministic)
    if registered:
        again = checks.check_model(rec, names, database, found.ordered)
        flagged = set(again.suspect)
        back = [n for n in registered if n not in flagged]
        if flagged - set(registered):  # a camera that was right looks wrong now: trust none of them
            back = []
        checks.leave_out(rec, [n for n in registered if n not in back])
    else:
        back = []
    staying = [n for n in suspect if n not in back]
    log.line(f"note: the {len(suspect)} suspect images registered again into the kept model: "
             f"{len(back)} came back ({shown_names(back, 4) or 'none'}), {len(staying)} stay out", show=True)
    return back, staying


def process_capture(inputs: list[Path], out: Path, config: ProcessConfig | None = None,
                    console: Console | None = None, replace_other: bool = False, summary: bool = True) -> dict:
    """Pose ``inputs`` into the COLMAP dataset ``out``; returns the report (also written to
    ``out/process_report.json``). Bad input is one DataError. ``replace_other``: an ``out`` that
    holds the processing of another input (a changed capture, in the cache) is redone. ``summary``:
    print the summary (also when every stage was done before)."""
    import pycolmap

    config = config or ProcessConfig()
    console = console or Console(stderr=True)
    capture = find_capture([Path(p).expanduser() for p in inputs], config.recursive)
    out = Path(out).expanduser()
    state = claim_output(out, capture, input_key(capture), replace_other)
    log = StageLog(out, console)
    threads = config.num_threads or default_threads()
    stages = _Stages(out, state, {
        "import": {"num_frames": config.num_frames if capture.kind == "videos" else None},
        "features": {"max_image_size": config.max_image_size, "camera_model": config.camera_model},
        "matching": {"matching": config.matching},
        "mapping": {"mapper": config.mapper, "remedy": config.remedy, "deterministic": config.deterministic},
    })
    images, database = out / "images", out / DATABASE_NAME
    if not stages.done("import"):
        if capture.note:  # which subfolders' photos are taken or left out, once, as they are imported
            log.line(capture.note, show=True)
        start = time.perf_counter()
        layout = _import(capture, images, config, console, log)
        stages.finish("import", time.perf_counter() - start, layout=asdict(layout))
    layout = _Layout(**state["stages"]["import"]["layout"])
    matching, why = choose_matching(config, capture, len(layout.names))
    with sfm.colmap_logs(config.verbose):
        if not stages.done("features"):
            database.unlink(missing_ok=True)
            state.pop("matches_in_database", None)
            start = time.perf_counter()
            mode = sfm.camera_mode(bool(layout.videos) and len(layout.videos) > 1, [tuple(s) for s in layout.sizes])
            with stage_progress(console, log, "features", len(layout.names), "images") as advance:
                sfm.extract(database, images, layout.names, mode, config.camera_model, config.max_image_size,
                            threads, advance)
            stages.finish("features", time.perf_counter() - start)
        if not stages.done("matching"):
            log.line(f"matching: {matching} ({why})", show=True)
            start = time.perf_counter()
            if state.get("matches_in_database") != matching:  # another --matching's pairs would stay
                sfm.clear_matches(database)
                state["matches_in_database"] = matching
                _write_state(out, state)
            recorded = _match(matching, layout, database, out, capture, threads, console, log)
            stages.finish("matching", time.perf_counter() - start, **recorded)
        if not stages.done("mapping"):
            start = time.perf_counter()
            # video frames are in capture order; photos: retrieval said, or the checks decide
            ordered = True if layout.videos else state["stages"]["matching"].get("ordered")
            recorded = _mapping(layout, database, images, out, matching, ordered, config, threads, console, log)
            stages.finish("mapping", time.perf_counter() - start, **recorded)
    mapped = state["stages"]["mapping"]
    rec = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    settings = {**asdict(config), "matching": matching, "mapper": mapped.get("mapper", config.mapper),
                "threads": threads}
    settings.pop("verbose")
    report = model_report(rec, layout.names, mapped.get("other_models", []), stages.seconds(), settings,
                          mapped.get("checks"), mapped.get("left_out", []), mapped.get("came_back", []))
    write_report(report, out)
    plot_top_view(rec, out / PLOT_NAME, suspect=mapped.get("checks", {}).get("suspect", []))
    for line in summary_lines(report) if summary else ():
        print(line, flush=True)
    if report["registered"] < MIN_REGISTERED_SHARE * report["images_in"]:
        raise DataError(out, f"only {report['registered']} of {report['images_in']} images registered "
                        "(under half); try photos with more overlap, --matching exhaustive or the other --mapper")
    return report
