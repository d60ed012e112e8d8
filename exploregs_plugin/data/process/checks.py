"""Is a posed model right? Checks that catch what a mean reprojection error does not.

Incremental SfM on a scene with repeated or symmetric structure can register a whole run of photos
on false but geometrically consistent matches (the duplicate-structure failure): the wrong cameras
and a ghost copy of the scene triangulated from them agree with each other, so the reprojection
error stays low (0.92 px on a 252-photo capture whose first quarter looked away from the object).
What does show it, without learned weights:

- **looks away** (orbits): the cameras of an object capture look at one place, the point nearest
  to all optical axes. A camera whose axis points more than 60 degrees away from it, while most
  cameras look straight at it, is posed wrong (the failure above: cosines of -0.4 to -1.0).
- **jumps** (captures with an order: video frames, photos whose consecutive names overlap): a
  step between consecutive cameras that the two images' own matches contradict. Neighbours in a
  capture order overlap for real, so their verified matches fit a right model (beer's and
  bonsai's right models: every consecutive pair, 70 and 251, at least 89% of its inliers); a
  block of cameras mapped onto false matches breaks the path where it meets the right ones, long
  step or not. Beer's 71 video frames, mapped from all pairs, turned by 172 degrees between
  frames 20 and 21 that look the same (none of their 160 inliers fits); a 24-view arc over a
  tiled floor, mapped by the global mapper, shifted its first 7 cameras by 30 degrees in a step
  as long as the others (half of the boundary pair's 395 inliers fit). The jumps cut the path
  into runs; runs whose near pairs (up to 10 apart in the order) mostly fit the model are one
  part, and the cameras outside the largest part are suspect. A long step the matches do not
  contradict is a gap (a capture may skip).
- **disagrees** (a warning): each strong verified pair of the database should satisfy the
  model's epipolar geometry; an image most of whose strong pairs contradict the model is listed.
  It does not fail a model: where the structure repeats, false pairs verify as strongly as true
  ones, and on beer the right model contradicted 120 of 367 strong pairs, the folded one 23.
- **weak** (a warning): images registered on few 3D points (often right, but held by little).

A model fails when any image is suspect (looks away or lies beyond a jump): both are physical
facts about a camera path, which false matches cannot vote away. The checks are pure functions
of the model and the database, deterministic, and take well under a second for 71 images.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import pycolmap

from .report import shown_names
from .sfm import SEQUENTIAL_OVERLAP

LOOK_AWAY_COS = 0.5
"""A camera looks away when cos(axis, direction to the common centre) < 0.5 (over 60 degrees)."""
ORBIT_MEDIAN_COS = 0.8
"""The looks-away check applies when the median camera looks within 37 degrees of the centre."""
STRONG_PAIR_INLIERS = 40
"""A verified pair with at least this many inlier matches is evidence about its two poses."""
AGREE_PX = 4.0
"""A match agrees with the model when its Sampson distance is within 4 px (verification's own
threshold)."""
AGREE_SHARE = 0.5
"""A pair agrees with the model when half of its inliers do: a wide-baseline pair's verified
inliers hold false matches too (the right model of a 24-view arc over a tiled floor fits pairs 8
to 10 views apart at 50-95%), and a fold contradicts all (beer's: none of 160)."""
NEIGHBOUR_AGREE_SHARE = 0.8
"""Consecutive images an ordinary step apart agree with the model when 80% of their inliers do:
seen from nearly one place, their matches are true (right models: at least 89% on beer's 70
consecutive pairs, 99% on bonsai's 251, 100% on the arc's 23), and the pair where a misplaced
block meets the right cameras fits a wrong model at 0 to 73% (a block shifted by 30 degrees kept
50-58%: half was not enough)."""
DISAGREE_SHARE = 0.5
"""An image disagrees when at least half of its strong pairs (and at least two) contradict the model."""
MAX_PAIRS_PER_IMAGE = 12
"""Each image's strongest pairs that are checked (enough evidence, bounded cost)."""
JUMP_FACTOR = 10.0
"""A step between consecutive cameras is a jump when it is 10x the median step and 3x the 90th
percentile step (bursts of photos from one spot shrink the median, not the 90th percentile)."""
JUMP_MIN_DEGREES = 45.0
"""... and a rotation step is a jump only above 45 degrees."""
SEAM_SHARE = 0.5
"""Consecutive images an ordinary step apart meet at a seam when the share of the 3D points of
the one with fewer that both see is under half the path's median share. Neighbours see the same
points: right models' smallest share was 77-92% of their median (beer 0.62 of 0.75, bonsai 0.50
of 0.65, a 101-frame desk video 0.35 of 0.44, the 24-view arc 0.60 of 0.65). Where two parts of
a model are held by few points, the step between them can stretch along its own direction, which
no epipolar constraint sees: the arc's global model kept 102 of 399 points (0.26 of 0.68) at the
step where its last 11 cameras sat 2-10% of the arc's width off."""
NEAR_WINDOW = SEQUENTIAL_OVERLAP
"""Images up to this far apart in a capture order are near: their matches are taken as true
(the neighbours matched by sequential matching)."""
LINK_INLIERS = 15
"""Two images share a verified pair when it has at least this many inliers."""
ORDER_SHARE = 0.8
"""Names are a capture order when 80% of consecutive registered images share a verified pair."""
WEAK_POINTS = 50
"""An image seen with fewer 3D points than this, or than 10% of the median image's, is weak."""


@dataclass
class ModelChecks:
    """What the checks found; ``suspect`` are the images the model should not be trusted on."""

    ordered: bool
    orbit: bool
    looks_away: list[str] = field(default_factory=list)
    disagrees: list[str] = field(default_factory=list)
    jumps: list[tuple[str, str]] = field(default_factory=list)
    seams: list[tuple[str, str]] = field(default_factory=list)
    gaps: list[tuple[str, str]] = field(default_factory=list)
    beyond_jumps: list[str] = field(default_factory=list)
    weak: list[str] = field(default_factory=list)
    pairs_checked: int = 0
    pairs_contradicted: int = 0

    @property
    def suspect(self) -> list[str]:
        return sorted(set(self.looks_away) | set(self.beyond_jumps))

    @property
    def passed(self) -> bool:
        return not self.suspect

    def to_dict(self) -> dict:
        return {**asdict(self), "jumps": [list(j) for j in self.jumps], "seams": [list(j) for j in self.seams],
                "gaps": [list(g) for g in self.gaps],
                "suspect": self.suspect,
                "passed": self.passed}


# ---------------------------------------------------------------------------------------------
# pure geometry


def axes_centre(centres: np.ndarray, axes: np.ndarray, iterations: int = 20) -> np.ndarray | None:
    """The point nearest to all optical axes (lines c_i + t d_i), robustly.

    Minimises sum_i w_i |(I - d_i d_i^T)(p - c_i)|^2; each iteration reweights w_i = 1 / max(r_i,
    eps) (Weiszfeld's scheme for lines: an L1 fit, so a quarter of wrong axes moves it little).
    None when the axes are (nearly) parallel: a forward-facing capture has no common centre."""
    d = axes / np.maximum(np.linalg.norm(axes, axis=1, keepdims=True), 1e-12)
    projectors = np.eye(3)[None] - d[:, :, None] * d[:, None, :]  # [n, 3, 3]
    weights = np.ones(len(d))
    scale = max(float(np.ptp(centres, axis=0).max()), 1e-9)
    point = None
    for _ in range(iterations):
        A = (weights[:, None, None] * projectors).sum(0)
        b = (weights[:, None, None] * projectors @ centres[:, :, None]).sum(0)[:, 0]
        eigenvalues = np.linalg.eigvalsh(A)
        if eigenvalues[0] <= 1e-3 * eigenvalues[-1]:  # no direction constrains the point
            return None
        point = np.linalg.solve(A, b)
        residual = np.linalg.norm((projectors @ (point - centres)[:, :, None])[:, :, 0], axis=1)
        weights = 1.0 / np.maximum(residual, 1e-6 * scale)
    return point


def look_cosines(centres: np.ndarray, axes: np.ndarray, target: np.ndarray) -> np.ndarray:
    """cos of the angle between each camera's axis and its direction to ``target``."""
    to_target = target[None] - centres
    norm = np.linalg.norm(to_target, axis=1) * np.linalg.norm(axes, axis=1)
    return (to_target * axes).sum(1) / np.maximum(norm, 1e-12)


def rotation_angle_deg(R1: np.ndarray, R2: np.ndarray) -> float:
    """The angle of R1 R2^T (trace = 1 + 2 cos angle), clipped against rounding."""
    cos = (np.trace(R1 @ R2.T) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


def find_jumps(positions: np.ndarray, rotations: np.ndarray) -> list[int]:
    """Indices i where the step i -> i+1 of an ordered path jumps (position or rotation)."""
    if len(positions) < 4:
        return []
    moves = np.linalg.norm(np.diff(positions, axis=0), axis=1)
    turns = np.array([rotation_angle_deg(rotations[i], rotations[i + 1]) for i in range(len(rotations) - 1)])

    def outliers(steps: np.ndarray, floor: float) -> np.ndarray:
        bound = max(JUMP_FACTOR * float(np.median(steps)), 3.0 * float(np.percentile(steps, 90)), floor)
        return steps > bound

    scale = max(float(np.ptp(positions, axis=0).max()), 1e-9)
    jumps = outliers(moves, 1e-6 * scale) | outliers(turns, JUMP_MIN_DEGREES)
    return [int(i) for i in np.flatnonzero(jumps)]


def beyond_jumps(count: int, jumps: list[int]) -> list[int]:
    """Indices on the wrong side of the jumps of a path of ``count`` cameras.

    Each jump of a folded model goes out to the wrong side or back, so the runs between jumps
    alternate: runs 0, 2, 4, ... are on one side and 1, 3, 5, ... on the other. The side with
    fewer cameras is the wrong one (ties: the side without the first camera). A run folded out and
    back (two jumps) is the odd run; a single jump leaves the smaller run beyond it."""
    bounds = [0] + [j + 1 for j in jumps] + [count]
    runs = [range(bounds[k], bounds[k + 1]) for k in range(len(bounds) - 1)]
    even = sum(len(r) for r in runs[0::2])
    wrong = runs[1::2] if even >= count - even else runs[0::2]
    return [i for r in wrong for i in r]


def wrong_runs(count: int, breaks: list[int], votes: list[tuple[int, int, bool]]) -> list[int]:
    """Indices of an ordered path of ``count`` cameras that lie off its main part.

    ``breaks``: steps i -> i+1 the two images' matches contradict; they cut the path into runs.
    ``votes``: (i, j, agrees) for pairs of images near each other in the order (neighbours that
    overlap for real), whether their matches fit the model.

    1. Runs are one part when more of the votes between them agree than contradict: the two
       sides of a short excursion meet again, a block shifted rigidly does not. Two runs a break
       separates are never one part, whatever the votes: a model bent rather than shifted (the
       first 13 of 24 cameras drifting by 5 to 17 degrees) kept most near pairs across its break.
    2. The part with the most cameras (ties: the earliest) is the main part.
    3. A part no vote ties to the main part either way (a long excursion: its far side is more
       than the window away; a tie) joins it when its runs are an even number of jumps from the
       main part's largest run: each jump of a fold goes out to the wrong side or comes back. A
       row of single cameras each at odds with both neighbours counts as one excursion (each
       is wrong on its own: a mirrored block contradicts itself at every step).
    So a path with a break always leaves cameras outside the main part, and they are returned."""
    if count == 0:
        return []
    run_of = np.zeros(count, dtype=np.int64)
    for i in sorted(set(breaks)):
        run_of[i + 1:] += 1
    n_runs = int(run_of[-1]) + 1
    balance = np.zeros((n_runs, n_runs), dtype=np.int64)
    for i, j, agrees in votes:
        a, b = int(run_of[i]), int(run_of[j])
        if a != b:
            balance[a, b] += 1 if agrees else -1
            balance[b, a] += 1 if agrees else -1
    parent = list(range(n_runs))

    def root(r: int) -> int:
        while parent[r] != r:
            parent[r] = parent[parent[r]]
            r = parent[r]
        return r

    def members(r: int) -> np.ndarray:
        return np.array([q for q in range(n_runs) if root(q) == root(r)])

    def apart(runs: np.ndarray, others: np.ndarray) -> bool:  # no break between the two sets
        return bool(np.abs(runs[:, None] - others[None, :]).min() > 1)

    for a, b in zip(*np.nonzero(np.triu(balance > 0))):
        if root(int(a)) != root(int(b)) and apart(members(int(a)), members(int(b))):
            parent[root(int(b))] = root(int(a))
    part_of = np.array([root(r) for r in range(n_runs)])
    run_sizes = np.bincount(run_of, minlength=n_runs)
    part_sizes = np.bincount(part_of, weights=run_sizes, minlength=n_runs)
    main = int(np.argmax(part_sizes))  # argmax: the first of equals, the part with the earliest cameras
    seed = max((r for r in range(n_runs) if part_of[r] == main), key=lambda r: (run_sizes[r], -r))
    # excursions: a row of single-camera runs is one
    single = run_sizes == 1
    excursion = np.cumsum([1] + [0 if single[r] and single[r - 1] else 1 for r in range(1, n_runs)])
    in_main = part_of == main
    for part in sorted(set(part_of.tolist()) - {main}):
        runs, main_runs = np.flatnonzero(part_of == part), np.flatnonzero(in_main)
        untied = not balance[np.ix_(runs, main_runs)].any()
        if untied and apart(runs, main_runs) and all((excursion[r] - excursion[seed]) % 2 == 0 for r in runs):
            in_main[runs] = True
    return [int(i) for i in np.flatnonzero(~in_main[run_of])]


def essential(R1: np.ndarray, t1: np.ndarray, R2: np.ndarray, t2: np.ndarray) -> tuple[np.ndarray, float]:
    """E = [t]x R of cam2_from_cam1 (x2^T E x1 = 0 for normalised points) and |t|."""
    R = R2 @ R1.T
    t = t2 - R @ t1
    tx = np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])
    return tx @ R, float(np.linalg.norm(t))


def sampson_distance(E: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """First-order geometric distance of normalised matches to the epipolar constraint:
    sqrt((x2^T E x1)^2 / ((E x1)_0^2 + (E x1)_1^2 + (E^T x2)_0^2 + (E^T x2)_1^2))."""
    h1 = np.concatenate([x1, np.ones((len(x1), 1))], axis=1)
    h2 = np.concatenate([x2, np.ones((len(x2), 1))], axis=1)
    Ex1, Etx2 = h1 @ E.T, h2 @ E
    num = (h2 * Ex1).sum(1) ** 2
    den = Ex1[:, 0] ** 2 + Ex1[:, 1] ** 2 + Etx2[:, 0] ** 2 + Etx2[:, 1] ** 2
    return np.sqrt(num / np.maximum(den, 1e-30))


# ---------------------------------------------------------------------------------------------
# the checks on a model


def _registered(rec: pycolmap.Reconstruction, names: list[str]) -> list:
    """The registered images in capture order (``names``), then any others by name."""
    images = {im.name: im for im in rec.images.values() if im.has_pose}
    rank = {n: i for i, n in enumerate(names)}
    return [images[n] for n in sorted(images, key=lambda n: (rank.get(n, len(rank)), n))]


def _pose(im) -> tuple[np.ndarray, np.ndarray]:
    m = im.cam_from_world().matrix()
    return m[:, :3], m[:, 3]


class _Matches:
    """The database's verified pairs, read once per check: inlier matches by (name1, name2) in
    the database's id order, and keypoints read on demand from the open database ``db``."""

    def __init__(self, db) -> None:
        self.db = db
        self.ids = {im.name: im.image_id for im in db.read_all_images()}
        names = {i: n for n, i in self.ids.items()}
        self.inliers = {}
        for pair_id, geometry in zip(*db.read_two_view_geometries()):
            id1, id2 = pycolmap.pair_id_to_image_pair(pair_id)
            self.inliers[(names[id1], names[id2])] = geometry.inlier_matches
        self._keypoints: dict[str, np.ndarray] = {}

    def keypoints(self, name: str) -> np.ndarray:
        if name not in self._keypoints:
            self._keypoints[name] = self.db.read_keypoints(self.ids[name])[:, :2].astype(np.float64)
        return self._keypoints[name]

    def count(self, n1: str, n2: str) -> int:
        """The verified inlier matches of ``n1`` and ``n2``: their number, 0 when under LINK_INLIERS."""
        n = len(self.inliers.get((n1, n2), self.inliers.get((n2, n1), ())))
        return n if n >= LINK_INLIERS else 0

    def coordinates(self, n1: str, n2: str) -> np.ndarray | None:
        """The verified inlier matches of ``n1`` and ``n2`` as keypoint coordinates [n, 4] (x1, y1,
        x2, y2), or None when the pair has fewer than LINK_INLIERS."""
        if not self.count(n1, n2):
            return None
        key = (n1, n2) if (n1, n2) in self.inliers else (n2, n1)
        inliers = self.inliers[key]
        xy = np.concatenate([self.keypoints(key[0])[inliers[:, 0]], self.keypoints(key[1])[inliers[:, 1]]], axis=1)
        return xy if key == (n1, n2) else xy[:, [2, 3, 0, 1]]

    def linked(self) -> set[frozenset]:
        """Unordered name pairs with a verified two-view geometry of at least LINK_INLIERS inliers."""
        return {frozenset(k) for k, inliers in self.inliers.items() if len(inliers) >= LINK_INLIERS}

    def strongest(self, registered: set[str]) -> list[tuple[str, str]]:
        """Each registered image's MAX_PAIRS_PER_IMAGE strongest pairs (at least
        STRONG_PAIR_INLIERS inliers) with other registered images; ties: lower ids first."""
        strong = sorted(((len(v), self.ids[a], self.ids[b], a, b) for (a, b), v in self.inliers.items()
                         if a in registered and b in registered and len(v) >= STRONG_PAIR_INLIERS),
                        key=lambda s: (-s[0], s[1], s[2]))
        kept_per_image: dict[str, int] = {}
        pairs = []
        for _, _, _, a, b in strong:
            if max(kept_per_image.get(a, 0), kept_per_image.get(b, 0)) >= MAX_PAIRS_PER_IMAGE:
                continue
            kept_per_image[a] = kept_per_image.get(a, 0) + 1
            kept_per_image[b] = kept_per_image.get(b, 0) + 1
            pairs.append((a, b))
        return pairs


class _Epipolar:
    """Whether matches fit a model's relative poses (its cameras and extent computed once)."""

    def __init__(self, rec: pycolmap.Reconstruction) -> None:
        self.rec = rec
        self.images = {im.name: im for im in rec.images.values() if im.has_pose}
        centres = np.array([im.projection_center() for im in self.images.values()]).reshape(-1, 3)
        self.extent = max(float(np.ptp(centres, axis=0).max()), 1e-9) if len(centres) else 1e-9

    def fit_share(self, n1: str, n2: str, xy: np.ndarray) -> float | None:
        """The share of the matches ``xy`` [n, 4] of images ``n1`` and ``n2`` that satisfy the
        model's epipolar geometry (Sampson distance within AGREE_PX); None when the model puts the
        two at one place (a rotation only: the epipolar constraint says nothing)."""
        im1, im2 = self.images[n1], self.images[n2]
        cam1, cam2 = self.rec.cameras[im1.camera_id], self.rec.cameras[im2.camera_id]
        (R1, t1), (R2, t2) = _pose(im1), _pose(im2)
        E, baseline = essential(R1, t1, R2, t2)
        if baseline < 1e-4 * self.extent:
            return None
        x1, x2 = cam1.cam_from_img(xy[:, :2]), cam2.cam_from_img(xy[:, 2:])
        # normalised units: AGREE_PX pixels over the mean focal length of the two cameras
        tolerance = AGREE_PX / max(0.5 * (cam1.mean_focal_length() + cam2.mean_focal_length()), 1e-9)
        return float(np.mean(sampson_distance(E, x1, x2) <= tolerance))

    def agrees(self, n1: str, n2: str, xy: np.ndarray) -> bool | None:
        """Whether the matches mostly fit the model (AGREE_SHARE of them); None: no evidence."""
        share = self.fit_share(n1, n2, xy)
        return None if share is None else share >= AGREE_SHARE


def _disagreeing(epipolar: _Epipolar, matches: _Matches) -> tuple[list[str], int, int]:
    """Images most of whose strong pairs contradict the model; how many strong pairs were
    checked, and how many contradict it."""
    pairs = matches.strongest(set(epipolar.images))
    votes: dict[str, list[bool]] = {}
    contradicted = 0
    for n1, n2 in pairs:
        agrees = epipolar.agrees(n1, n2, matches.coordinates(n1, n2))
        if agrees is None:
            continue
        contradicted += not agrees
        votes.setdefault(n1, []).append(agrees)
        votes.setdefault(n2, []).append(agrees)
    flagged = [n for n, v in votes.items() if v.count(False) >= max(2, DISAGREE_SHARE * len(v))]
    return sorted(flagged), len(pairs), contradicted


def _is_ordered(images: list, pairs_any: set[frozenset]) -> bool:
    """Whether consecutive registered images (in name order) mostly share a verified pair."""
    if len(images) < 4:
        return False
    linked = sum(frozenset((a.name, b.name)) in pairs_any for a, b in zip(images, images[1:]))
    return linked >= ORDER_SHARE * (len(images) - 1)


def weak_floor(counts: list[int] | np.ndarray) -> float:
    """Images seen with fewer 3D points than this are weak: WEAK_POINTS, or 10% of the median
    image's count where that is more."""
    return max(WEAK_POINTS, 0.1 * float(np.median(counts))) if len(counts) else float(WEAK_POINTS)


def seam_steps(images: list, inliers: list[int | None] | None = None) -> list[int]:
    """Steps i -> i+1 of a capture order whose two images share few 3D points (SEAM_SHARE): of
    the points the one with fewer sees, or, with ``inliers`` (each step's verified inlier count,
    None where the pair has none), of the matches the two verified. The second sees an end camera
    stretched away along its step: the arc's global model put its first camera 4.5 median steps
    out with 191 points, and kept 148 of the 473 inliers it shares with the second as common
    points (0.31, against a median of 0.89; right models' smallest: 0.67-0.80 of their median)."""
    if len(images) < 4:
        return []
    seen = [{p.point3D_id for p in im.points2D if p.has_point3D()} for im in images]
    shared = np.array([len(a & b) for a, b in zip(seen, seen[1:])], dtype=np.float64)
    of_seen = shared / np.maximum([min(len(a), len(b)) for a, b in zip(seen, seen[1:])], 1)
    low = of_seen < SEAM_SHARE * float(np.median(of_seen))
    if inliers is not None:
        matched = np.array([n if n else np.nan for n in inliers], dtype=np.float64)
        of_matched = shared / matched
        if np.isfinite(of_matched).any():
            low |= of_matched < SEAM_SHARE * float(np.nanmedian(of_matched))  # NaN compares False
    return [int(i) for i in np.flatnonzero(low)]


def check_poses(rec: pycolmap.Reconstruction, names: list[str], ordered: bool,
                fits: Callable[[str, str], float | None] | None = None,
                inliers: Callable[[str, str], int] | None = None) -> ModelChecks:
    """The checks that need only the model: looks away, jumps (when ``ordered``: ``names`` are a
    capture order) and weak images.

    ``fits(a, b)``: the share of two images' matches that fit the model (None: no evidence).
    Every consecutive step the matches contradict is a jump, long or not: an ordinary step below
    NEIGHBOUR_AGREE_SHARE (a block shifted by 30 degrees kept half), a long step below
    AGREE_SHARE (beer's folded frames 20 and 21 share 160 inliers, none of which fits the
    model's 172-degree turn). A long step is not always a fold: a capture can skip (fox's frames
    54 to 68 are 14 median steps and 43 degrees apart, rightly), and a skip's wide-baseline
    matches fit less well, so a long step they do not contradict is a gap (a warning). The pairs
    up to NEAR_WINDOW apart decide which runs between jumps are one part (``wrong_runs``).
    ``inliers(a, b)``: the verified inlier count of two images, for the seams (``seam_steps``).
    Without ``fits`` (no database), only long steps count, only when they go out and come back
    (two or more), and the runs beyond them alternate (``beyond_jumps``)."""
    images = _registered(rec, names)
    centres = np.array([im.projection_center() for im in images]).reshape(-1, 3)
    axes = np.array([im.viewing_direction() for im in images]).reshape(-1, 3)
    checks = ModelChecks(ordered=ordered, orbit=False)
    if len(images) >= 3:
        centre = axes_centre(centres, axes)
        if centre is not None:
            cos = look_cosines(centres, axes, centre)
            checks.orbit = bool(np.median(cos) >= ORBIT_MEDIAN_COS)
            if checks.orbit:
                checks.looks_away = sorted(im.name for im, c in zip(images, cos) if c < LOOK_AWAY_COS)
    if ordered:
        rotations = np.array([_pose(im)[0] for im in images]).reshape(-1, 3, 3)
        steps = find_jumps(centres, rotations)
        if fits is not None:
            shares = {(i, j): share for i in range(len(images)) for j in range(i + 1, min(i + NEAR_WINDOW + 1, len(images)))
                      if (share := fits(images[i].name, images[j].name)) is not None}
            jumps = [i for (i, j), share in shares.items()
                     if j == i + 1 and share < (AGREE_SHARE if i in steps else NEIGHBOUR_AGREE_SHARE)]
            counts = None if inliers is None else [inliers(a.name, b.name) for a, b in zip(images, images[1:])]
            seams = [i for i in seam_steps(images, counts) if i not in steps and i not in jumps]
            checks.seams = [(images[i].name, images[i + 1].name) for i in seams]
            votes = [(i, j, share >= AGREE_SHARE) for (i, j), share in shares.items()]
            wrong = wrong_runs(len(images), jumps + seams, votes)
        else:
            jumps = steps if len(steps) >= 2 else []
            wrong = beyond_jumps(len(images), jumps)
        checks.jumps = [(images[i].name, images[i + 1].name) for i in jumps]
        checks.gaps = [(images[i].name, images[i + 1].name) for i in steps if i not in jumps]
        checks.beyond_jumps = sorted(images[i].name for i in wrong)
    floor = weak_floor([im.num_points3D for im in images])
    checks.weak = sorted(im.name for im in images if im.num_points3D < floor)
    return checks


def check_model(rec: pycolmap.Reconstruction, names: list[str], database: Path,
                ordered: bool | None = None) -> ModelChecks:
    """Run every check on ``rec`` (images ``names`` in capture order; ``database`` holds the
    matches it was mapped from). ``ordered``: whether names are a capture order (video frames:
    True); None decides from the matches."""
    epipolar = _Epipolar(rec)
    with pycolmap.Database.open(database) as db:
        matches = _Matches(db)
        if ordered is None:
            ordered = _is_ordered(_registered(rec, names), matches.linked())

        def fits(a: str, b: str) -> float | None:
            xy = matches.coordinates(a, b)
            return None if xy is None else epipolar.fit_share(a, b, xy)

        checks = check_poses(rec, names, ordered, fits, matches.count)
        checks.disagrees, checks.pairs_checked, checks.pairs_contradicted = _disagreeing(epipolar, matches)
    return checks


def folded_warning(rec: pycolmap.Reconstruction, where: object) -> str | None:
    """A warning for a COLMAP model read for training whose camera path looks folded (cameras
    that look away from an orbit's centre, or jumps along the name order), else None. Photos in
    random name order make no jumps (every step is as long as the median), so name order is
    taken as the capture order."""
    names = sorted(im.name for im in rec.images.values() if im.has_pose)
    found = check_poses(rec, names, ordered=True)
    if found.passed:
        return None
    parts = []
    if found.jumps:
        shown = ", ".join(f"{a} -> {b}" for a, b in found.jumps[:3]) + (" ..." if len(found.jumps) > 3 else "")
        parts.append(f"{len(found.jumps)} jumps along the name order ({shown})")
    if found.looks_away:
        parts.append(f"{len(found.looks_away)} cameras looking away from the others' common centre")
    return (f"{where}: the camera poses look folded ({'; '.join(parts)}; {len(found.suspect)} of {len(names)} "
            "cameras suspect): repeated or symmetric structure can fold a model; the photos can be posed again "
            "with `eg-process IMAGES --out NEW`, which checks and remedies this")


def leave_out(rec: pycolmap.Reconstruction, names: list[str]) -> int:
    """De-register the images ``names`` from ``rec`` (their observations go, and the points left
    with fewer than two); returns how many were removed."""
    removed = 0
    for im in list(rec.images.values()):
        if im.name in names and im.has_pose:
            rec.deregister_frame(im.frame_id)
            removed += 1
    return removed


def check_lines(checks: ModelChecks, registered: int) -> list[str]:
    """The summary's lines about the checks (one when all is well)."""
    parts = [f"{len(checks.looks_away)} look away from the common centre" if checks.orbit
             else "not an orbit (no look-away check)",
             f"{len(checks.disagrees)} disagree with their matched views ({checks.pairs_contradicted} of "
             f"{checks.pairs_checked} strong pairs contradicted)"]
    if checks.ordered:
        parts.append(f"{len(checks.jumps)} jumps along the capture order")
        if checks.seams:
            parts.append(f"{len(checks.seams)} seams")
    verdict = "passed" if checks.passed else f"failed, {len(checks.suspect)} suspect"
    lines = [f"checks ({verdict}): {registered} cameras: " + ", ".join(parts)]
    if checks.looks_away:
        lines.append(f"  look away: {shown_names(checks.looks_away, 6)}")
    if checks.disagrees:
        lines.append(f"  disagree (a warning): {shown_names(checks.disagrees, 6)}")
    for a, b in checks.jumps[:6]:
        lines.append(f"  jump between {a} and {b}")
    for a, b in checks.seams[:6]:
        lines.append(f"  seam between {a} and {b} (neighbours that share few 3D points)")
    for a, b in checks.gaps[:6]:
        lines.append(f"  gap between {a} and {b} (a long step their matches do not contradict; a warning)")
    if checks.weak:
        lines.append(f"  weak (few 3D points; a warning): {shown_names(checks.weak, 6)}")
    return lines
