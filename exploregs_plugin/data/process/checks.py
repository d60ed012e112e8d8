"""Is a posed model right? Checks that catch what a mean reprojection error does not.

Incremental SfM on a scene with repeated or symmetric structure can register a whole run of photos
on false but geometrically consistent matches (the duplicate-structure failure): the wrong cameras
and a ghost copy of the scene triangulated from them agree with each other, so the reprojection
error stays low (0.92 px on a 252-photo capture whose first quarter looked away from the object).
What does show it, without learned weights:

- **looks away** (orbits): the cameras of an object capture look at one place, the point nearest
  to all optical axes. A camera whose axis points more than 60 degrees away from it, while most
  cameras look straight at it, is posed wrong (the failure above: cosines of -0.4 to -1.0).
- **jumps** (captures with an order: video frames, photos whose consecutive names overlap): the
  path between consecutive cameras jumps far beyond its usual step, in rotation or position.
  A long step counts as a jump when the two images' own matches contradict the model (a capture
  may skip; a fold turns cameras that see the same thing). The cameras on the smaller side of the
  jumps are suspect. Beer's 71 video frames, mapped
  from all pairs, turned by 172 degrees between frames 20 and 21 that look the same.
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

LOOK_AWAY_COS = 0.5
"""A camera looks away when cos(axis, direction to the common centre) < 0.5 (over 60 degrees)."""
ORBIT_MEDIAN_COS = 0.8
"""The looks-away check applies when the median camera looks within 37 degrees of the centre."""
STRONG_PAIR_INLIERS = 40
"""A verified pair with at least this many inlier matches is evidence about its two poses."""
AGREE_PX = 4.0
"""A match agrees with the model when its Sampson distance is within 4 px (verification's own
threshold); a pair agrees when half of its inliers do."""
DISAGREE_SHARE = 0.5
"""An image disagrees when at least half of its strong pairs (and at least two) contradict the model."""
MAX_PAIRS_PER_IMAGE = 12
"""Each image's strongest pairs that are checked (enough evidence, bounded cost)."""
JUMP_FACTOR = 10.0
"""A step between consecutive cameras is a jump when it is 10x the median step and 3x the 90th
percentile step (bursts of photos from one spot shrink the median, not the 90th percentile)."""
JUMP_MIN_DEGREES = 45.0
"""... and a rotation step is a jump only above 45 degrees."""
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
        return {**asdict(self), "jumps": [list(j) for j in self.jumps], "gaps": [list(g) for g in self.gaps],
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

    def coordinates(self, n1: str, n2: str) -> np.ndarray | None:
        """The verified inlier matches of ``n1`` and ``n2`` as keypoint coordinates [n, 4] (x1, y1,
        x2, y2), or None when the pair has fewer than LINK_INLIERS."""
        key = (n1, n2) if (n1, n2) in self.inliers else (n2, n1)
        inliers = self.inliers.get(key, np.zeros((0, 2), np.uint32))
        if len(inliers) < LINK_INLIERS:
            return None
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

    def agrees(self, n1: str, n2: str, xy: np.ndarray) -> bool | None:
        """Whether the matches ``xy`` [n, 4] of images ``n1`` and ``n2`` mostly satisfy the
        model's epipolar geometry (Sampson distance within AGREE_PX for half of them); None when
        the model puts the two at one place (a rotation only: the epipolar constraint says
        nothing)."""
        im1, im2 = self.images[n1], self.images[n2]
        cam1, cam2 = self.rec.cameras[im1.camera_id], self.rec.cameras[im2.camera_id]
        (R1, t1), (R2, t2) = _pose(im1), _pose(im2)
        E, baseline = essential(R1, t1, R2, t2)
        if baseline < 1e-4 * self.extent:
            return None
        x1, x2 = cam1.cam_from_img(xy[:, :2]), cam2.cam_from_img(xy[:, 2:])
        # normalised units: AGREE_PX pixels over the mean focal length of the two cameras
        tolerance = AGREE_PX / max(0.5 * (cam1.mean_focal_length() + cam2.mean_focal_length()), 1e-9)
        return float(np.mean(sampson_distance(E, x1, x2) <= tolerance)) >= 0.5


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


def check_poses(rec: pycolmap.Reconstruction, names: list[str], ordered: bool,
                folded: Callable[[str, str], bool] | None = None) -> ModelChecks:
    """The checks that need only the model: looks away, jumps (when ``ordered``: ``names`` are a
    capture order) and weak images.

    A long step is not always a fold: a capture can skip (fox's frames 54 to 68 are 14 median steps
    and 43 degrees apart, rightly). ``folded(a, b)`` says whether the model contradicts the
    matches of two consecutive images (beer's folded frames 20 and 21 share 160 inliers, none of
    which fits the model's 172-degree turn; frames that fit agree 100%); a long step it does not
    confirm is a gap (a warning). Without it (no database), only jumps that go out and come back
    (two or more) count."""
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
        if folded is not None:
            jumps = [i for i in steps if folded(images[i].name, images[i + 1].name)]
        else:
            jumps = steps if len(steps) >= 2 else []
        checks.jumps = [(images[i].name, images[i + 1].name) for i in jumps]
        checks.gaps = [(images[i].name, images[i + 1].name) for i in steps if i not in jumps]
        checks.beyond_jumps = sorted(images[i].name for i in beyond_jumps(len(images), jumps))
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

        def folded(a: str, b: str) -> bool:
            xy = matches.coordinates(a, b)
            return xy is not None and epipolar.agrees(a, b, xy) is False

        checks = check_poses(rec, names, ordered, folded)
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
    verdict = "passed" if checks.passed else f"failed, {len(checks.suspect)} suspect"
    lines = [f"checks ({verdict}): {registered} cameras: " + ", ".join(parts)]
    if checks.looks_away:
        lines.append(f"  look away: {shown_names(checks.looks_away, 6)}")
    if checks.disagrees:
        lines.append(f"  disagree (a warning): {shown_names(checks.disagrees, 6)}")
    for a, b in checks.jumps[:6]:
        lines.append(f"  jump between {a} and {b}")
    for a, b in checks.gaps[:6]:
        lines.append(f"  gap between {a} and {b} (a long step their matches do not contradict; a warning)")
    if checks.weak:
        lines.append(f"  weak (few 3D points; a warning): {shown_names(checks.weak, 6)}")
    return lines
