"""The pycolmap stages: features (SIFT), matching (pairs chosen here), mapping (incremental or
global). Each works on the database in the output folder and can be cut at any point: extraction
skips images that have features, matching skips pairs already matched.

pycolmap's calls take one chunk of images or pairs at a time, so a progress bar advances between
chunks; every call gets the thread count explicitly.
"""

from __future__ import annotations

import contextlib
import itertools
import math
import shutil
from pathlib import Path
from typing import Callable, Iterator, Literal, Sequence

import pycolmap

from .config import Mapper

Matching = Literal["exhaustive", "sequential", "spatial", "retrieval"]
SEQUENTIAL_OVERLAP = 10
"""Sequential matching pairs each frame with the next 10 and with those 2^k frames ahead."""
CROSS_VIDEO_KEYFRAMES = 30
"""Between different videos, this many evenly spaced frames of each are matched exhaustively."""


@contextlib.contextmanager
def colmap_logs(verbose: bool) -> Iterator[None]:
    """pycolmap's own log lines: all of them to stderr with ``verbose``, none otherwise."""
    log = pycolmap.logging
    before = (log.minloglevel, log.logtostderr)
    log.minloglevel = 0 if verbose else 3  # glog levels: 0 INFO, 1 WARNING, 2 ERROR, 3 FATAL
    log.logtostderr = verbose
    try:
        yield
    finally:
        log.minloglevel, log.logtostderr = before


def option_groups(options, depth: int = 4) -> list:
    """``options`` and the option groups nested in it (pycolmap's ``...Options`` attributes), down to
    ``depth`` levels."""
    groups = [options]
    if depth > 0:
        for name in dir(options):
            if not name.startswith("_") and type(getattr(options, name)).__name__.endswith("Options"):
                groups += option_groups(getattr(options, name), depth - 1)
    return groups


def with_threads(options, threads: int):
    """``options`` with every ``num_threads`` in it, nested option groups included, set to
    ``threads`` (pycolmap's -1 means every core, which a shared machine does not have)."""
    for group in option_groups(options):
        if hasattr(group, "num_threads"):
            group.num_threads = threads
    return options


def chunks(items: Sequence, count: int) -> list[Sequence]:
    """``items`` in about ``count`` consecutive chunks (each non-empty)."""
    size = max(1, math.ceil(len(items) / max(count, 1)))
    return [items[i:i + size] for i in range(0, len(items), size)]


def camera_mode(per_folder: bool, sizes: Sequence[tuple[int, int]]) -> pycolmap.CameraMode:
    """One camera per video (frames in one folder per video), one for same-sized photos, else one
    per photo."""
    if per_folder:
        return pycolmap.CameraMode.PER_FOLDER
    return pycolmap.CameraMode.SINGLE if len(set(sizes)) <= 1 else pycolmap.CameraMode.PER_IMAGE


def extract(database: Path, image_dir: Path, names: list[str], mode: pycolmap.CameraMode, camera_model: str,
            max_image_size: int, threads: int, advance: Callable[[int], None]) -> None:
    """Import every image (its camera from ``mode``) into the database, then SIFT in chunks."""
    pycolmap.Database.open(database).close()  # pycolmap's import wants the file to exist
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = camera_model
    with pycolmap.Database.open(database) as db:
        missing = [n for n in names if not db.exists_image(n)] if db.num_images() else names
    if missing:
        pycolmap.import_images(database, image_dir, camera_mode=mode, image_names=missing, options=reader)
    options = pycolmap.FeatureExtractionOptions()
    options.max_image_size = max_image_size
    options.num_threads = threads
    for chunk in chunks(names, min(10, math.ceil(len(names) / 16))):  # a call costs about 1 s to set up
        pycolmap.extract_features(database, image_dir, image_names=list(chunk), reader_options=reader,
                                  extraction_options=options, device=pycolmap.Device.cpu)
        advance(len(chunk))


def exhaustive_pairs(names: Sequence[str]) -> list[tuple[str, str]]:
    return list(itertools.combinations(names, 2))


def sequential_pairs(names: Sequence[str], overlap: int = SEQUENTIAL_OVERLAP) -> list[tuple[str, str]]:
    """Each frame with the next ``overlap`` and with the frames 2^k ahead (loops of a walk)."""
    offsets = set(range(1, overlap + 1)) | {2 ** k for k in range(overlap) if 2 ** k < len(names)}
    return [(names[i], names[i + o]) for i in range(len(names)) for o in sorted(offsets) if i + o < len(names)]


def video_pairs(videos: Sequence[Sequence[str]]) -> list[tuple[str, str]]:
    """Sequential pairs inside each video, and keyframes of different videos all against all."""
    pairs = [p for frames in videos for p in sequential_pairs(frames)]
    keyframes = [list(frames[::max(1, len(frames) // CROSS_VIDEO_KEYFRAMES)]) for frames in videos]
    for a, b in itertools.combinations(range(len(videos)), 2):
        pairs += [(x, y) for x in keyframes[a] for y in keyframes[b]]
    return pairs


def verification_options() -> pycolmap.TwoViewGeometryOptions:
    """Two-view geometric verification with a fixed RANSAC seed. pycolmap's default (-1) seeds
    each verification from the clock, so the inliers kept, and the model mapped from them,
    changed from run to run whenever matching ran on more than one thread."""
    options = pycolmap.TwoViewGeometryOptions()
    options.ransac.random_seed = 0
    return options


def match_pairs(database: Path, pairs: list[tuple[str, str]], pairs_file: Path, threads: int,
                advance: Callable[[int], None]) -> None:
    """Match and verify ``pairs`` in chunks (pycolmap reads each chunk from ``pairs_file``)."""
    options = pycolmap.FeatureMatchingOptions()
    options.num_threads = threads
    verification = verification_options()
    for chunk in chunks(pairs, min(25, math.ceil(len(pairs) / 100))):  # a call costs about 0.1 s
        pairs_file.write_text("".join(f"{a} {b}\n" for a, b in chunk))
        pairing = pycolmap.ImportedPairingOptions()
        pairing.match_list_path = str(pairs_file)
        pycolmap.match_image_pairs(database, matching_options=options, pairing_options=pairing,
                                   verification_options=verification, device=pycolmap.Device.cpu)
        advance(len(chunk))


def pose_prior_count(database: Path) -> int:
    with pycolmap.Database.open(database) as db:
        return db.num_pose_priors()


def match_spatial(database: Path, threads: int) -> None:
    """Pairs of photos near each other by their GPS positions (pycolmap's spatial matcher)."""
    options = pycolmap.FeatureMatchingOptions()
    options.num_threads = threads
    pairing = pycolmap.SpatialPairingOptions()
    pairing.num_threads = threads
    pycolmap.match_spatial(database, matching_options=options, pairing_options=pairing,
                           verification_options=verification_options(), device=pycolmap.Device.cpu)


def map_scene(database: Path, image_dir: Path, out_dir: Path, mapper: Mapper, threads: int, deterministic: bool,
              on_registered: Callable[[int], None]) -> dict[int, pycolmap.Reconstruction]:
    """Every model the mapper finds, written to ``out_dir/<index>``; ``on_registered(n)`` reports
    the images the incremental mapper registers (the global one reports nothing until done).

    ``deterministic``: the pipeline and every solver inside it (the mapper, the global mapper's
    bundle adjustment in Ceres) on one thread. Bundle adjustment's sums on several threads come in
    a varying order: on two threads 12 photos gave 444, 505 or 710 points from run to run
    (incremental), or the same points at other bits (global); with the pipeline alone on one thread
    the solvers inside it still ran on ``threads``, and now and then (two test runs in about a
    dozen) the model of two threads differed from that of one. On one thread throughout the model
    is the same bits for any ``threads``. Off by default: it is speed the user pays for and does not
    see."""
    out_dir.mkdir(parents=True, exist_ok=True)
    pycolmap.set_random_seed(0)  # the same capture gives the same model (up to thread order)
    pipeline = pycolmap.GlobalPipelineOptions() if mapper == "global" else pycolmap.IncrementalPipelineOptions()
    options = with_threads(pipeline, 1 if deterministic else threads)
    options.random_seed = 0
    if mapper == "global":
        return pycolmap.global_mapping(database, image_dir, out_dir, options=options)
    return pycolmap.incremental_mapping(database, image_dir, out_dir, options=options,
                                        initial_image_pair_callback=lambda: on_registered(2),
                                        next_image_callback=lambda: on_registered(1))


def register_into(database: Path, rec: pycolmap.Reconstruction, names: Sequence[str], threads: int,
                  deterministic: bool = False) -> list[str]:
    """Register the images ``names`` of ``rec`` (present, without a pose) into it, in that order, from
    their matches in ``database`` to the points ``rec`` holds (pycolmap's incremental mapper: an
    absolute pose from the 2D-3D correspondences, then triangulation of the image's other
    observations); no bundle adjustment, so the model's other cameras keep their poses. Returns
    the names registered. ``rec`` is changed in place. ``deterministic``: on one thread, as
    :func:`map_scene` (the pose refinement's sums come in a fixed order)."""
    with pycolmap.Database.open(database) as db:
        cache = pycolmap.DatabaseCache.create(db, pycolmap.DatabaseCacheOptions())
    mapper = pycolmap.IncrementalMapper(cache)
    mapper.begin_reconstruction(rec)
    options = pycolmap.IncrementalMapperOptions()
    options.num_threads = 1 if deterministic else threads
    options.random_seed = 0  # the same model gives the same poses (up to thread order)
    triangulation = pycolmap.IncrementalTriangulatorOptions()
    registered = []
    try:
        for name in names:
            image = rec.find_image_with_name(name)
            if image is None or image.has_pose or not mapper.register_next_image(options, image.image_id):
                continue
            mapper.triangulate_image(triangulation, image.image_id)
            registered.append(name)
    finally:
        mapper.end_reconstruction(False)
    return registered


def clear_matches(database: Path) -> None:
    """Remove every match and two-view geometry (the features stay)."""
    with pycolmap.Database.open(database) as db:
        db.clear_matches()
        db.clear_two_view_geometries()


def matched_pairs(database: Path) -> set[frozenset]:
    """The unordered name pairs the database holds matches or a two-view geometry for (a pair
    matched with too few matches leaves no row: the caller adds the pairs it asked for)."""
    with pycolmap.Database.open(database) as db:
        names = {im.image_id: im.name for im in db.read_all_images()}
        pair_ids = set(db.read_all_matches()[0]) | set(db.read_two_view_geometries()[0])
    return {frozenset(names[i] for i in pycolmap.pair_id_to_image_pair(p)) for p in pair_ids}


def window_database(database: Path, target: Path, names: Sequence[str], window: int = SEQUENTIAL_OVERLAP) -> int:
    """A copy of ``database`` at ``target`` that keeps only the matches between images at most
    ``window`` apart in ``names`` (capture order); returns how many pairs it dropped.

    The remedy for a capture with an order whose model failed its checks: a long-range pair
    between two views of repeated or symmetric structure (the two sides of a can on a tiled
    floor) can verify as well as a true one and fold a run of cameras onto the wrong side; the
    neighbours of a walk or a video overlap for real."""
    shutil.copyfile(database, target)
    rank = {n: i for i, n in enumerate(names)}
    dropped = 0
    with pycolmap.Database.open(target) as db:
        ids = {im.image_id: im.name for im in db.read_all_images()}
        pair_ids, _ = db.read_two_view_geometries()
        for pair_id in pair_ids:
            a, b = pycolmap.pair_id_to_image_pair(pair_id)
            if abs(rank.get(ids[a], -10 ** 9) - rank.get(ids[b], 10 ** 9)) > window:
                db.delete_two_view_geometry(a, b)
                db.delete_matches(a, b)
                dropped += 1
    return dropped
