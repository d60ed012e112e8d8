"""How close a posed capture is to a reference: similarity-align the camera centres, then count
the cameras within an angle and a share of the camera extent (eg-process's measure on captures
whose reference poses are published).

    python -m exploregs_plugin.bench.components.pose_agreement outputs/process/bonsai252 REF [--reference-kind llff]

REF is a COLMAP model folder (``sparse/0``, or a dataset that holds one), a ``transforms.json``,
or an LLFF ``poses_bounds.npy`` (the Mip-NeRF 360 release's; rows in image-name order of ``--names-from``).
Prints one table row: cameras compared, within 2 degrees and 2% of the extent, the median and
largest errors. Centres are compared after the similarity that most centres agree with;
orientations after the rotation that best aligns them.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

ANGLE_DEG = 2.0
EXTENT_SHARE = 0.02


def umeyama(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Similarity (s, R, t) minimising sum |s R src_i + t - dst_i|^2 (Umeyama 1991); the scale's
    denominator (the source's variance) is guarded."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    U, S, Vt = np.linalg.svd(xd.T @ xs / len(src))
    D = np.eye(3)
    D[2, 2] = np.sign(np.linalg.det(U @ Vt)) or 1.0
    R = U @ D @ Vt
    s = float(np.trace(np.diag(S) @ D) / max((xs ** 2).sum(1).mean(), 1e-12))
    return s, R, mu_d - s * R @ mu_s


def robust_similarity(src: np.ndarray, dst: np.ndarray, extent: float, tolerance: float = 0.05):
    """The similarity that most centres agree with (within ``tolerance`` x ``extent``): candidate
    fits on all centres and on every run of a quarter of them in order, the one with the most
    agreeing centres refitted on those, twice. A folded or misplaced quarter would pull a single
    fit on all centres towards itself (deterministic, no random sampling)."""
    n = len(src)
    run = max(3, n // 4)
    subsets = [np.arange(n)] + [np.arange(i, i + run) % n for i in range(n)]
    best, best_count = None, -1
    for subset in subsets:
        s, R, t = umeyama(src[subset], dst[subset])
        count = int((np.linalg.norm(s * src @ R.T + t - dst, axis=1) <= tolerance * extent).sum())
        if count > best_count:
            best, best_count = (s, R, t), count
    for _ in range(2):
        s, R, t = best
        keep = np.linalg.norm(s * src @ R.T + t - dst, axis=1) <= tolerance * extent
        if keep.sum() >= 3:
            best = umeyama(src[keep], dst[keep])
    return best


def orientation_alignment(est: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """The rotation Q minimising sum |Q R_est_i - R_ref_i|_F^2 (the chordal mean of R_ref_i
    R_est_i^T, projected onto SO(3) by an SVD with the determinant's sign fixed)."""
    M = np.einsum("vij,vkj->ik", ref, est)
    U, _, Vt = np.linalg.svd(M)
    D = np.eye(3)
    D[2, 2] = np.sign(np.linalg.det(U @ Vt)) or 1.0
    return U @ D @ Vt


def agreement(estimated: dict[str, np.ndarray], reference: dict[str, np.ndarray]) -> dict:
    """Camera-to-world [4, 4] (OpenCV axes) by image name, both; compares the names in both."""
    names = sorted(set(estimated) & set(reference))
    if len(names) < 3:
        raise ValueError(f"{len(names)} cameras in common; at least 3 are needed")
    est = np.stack([estimated[n] for n in names])
    ref = np.stack([reference[n] for n in names])
    extent = max(float(np.linalg.norm(ref[:, None, :3, 3] - ref[None, :, :3, 3], axis=2).max()), 1e-12)
    s, R, t = robust_similarity(est[:, :3, 3], ref[:, :3, 3], extent)
    centre_error = np.linalg.norm(s * est[:, :3, 3] @ R.T + t - ref[:, :3, 3], axis=1) / extent
    # rotation error: the angle of R_ref^T (Q R_est), trace = 1 + 2 cos(angle), with Q the rotation
    # that best aligns the orientations (the chordal mean of R_ref R_est^T, projected onto SO(3)):
    # the centres of a short arc fix the similarity's rotation poorly about the arc's own axis
    Q = orientation_alignment(est[:, :3, :3], ref[:, :3, :3])
    rel = np.einsum("vji,jk,vkl->vil", ref[:, :3, :3], Q, est[:, :3, :3])
    angle = np.degrees(np.arccos(np.clip((np.trace(rel, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)))
    good = (angle <= ANGLE_DEG) & (centre_error <= EXTENT_SHARE)
    return {
        "compared": len(names), "reference": len(reference), "within": int(good.sum()),
        "share_within": round(float(good.mean()), 4),
        "median_angle_deg": round(float(np.median(angle)), 3), "max_angle_deg": round(float(angle.max()), 3),
        "median_centre_error": round(float(np.median(centre_error)), 5),
        "max_centre_error": round(float(centre_error.max()), 5),
        "worst": [names[i] for i in np.argsort(-(angle / ANGLE_DEG + centre_error / EXTENT_SHARE))[:5]],
    }


def colmap_cameras(path: Path) -> dict[str, np.ndarray]:
    """Camera-to-world [4, 4] by name from a COLMAP model (or a dataset folder's sparse/0)."""
    import pycolmap

    folder = path / "sparse" / "0" if (path / "sparse" / "0").is_dir() else path
    rec = pycolmap.Reconstruction(str(folder))
    out = {}
    for im in rec.images.values():
        if im.has_pose:
            w2c = np.eye(4)
            w2c[:3, :4] = im.cam_from_world().matrix()
            out[im.name] = np.linalg.inv(w2c)
    return out


def transforms_cameras(path: Path) -> dict[str, np.ndarray]:
    """Camera-to-world [4, 4] in OpenCV axes by file name from a transforms.json (OpenGL axes:
    c2w_cv = c2w_gl diag(1, -1, -1, 1))."""
    frames = json.loads(path.read_text())["frames"]
    flip = np.diag([1.0, -1.0, -1.0, 1.0])
    return {Path(f["file_path"]).name: np.asarray(f["transform_matrix"], dtype=np.float64) @ flip for f in frames}


def llff_cameras(poses_bounds: Path, names: list[str]) -> dict[str, np.ndarray]:
    """Camera-to-world [4, 4] in OpenCV axes from an LLFF ``poses_bounds.npy`` whose rows are the
    sorted ``names``. LLFF's columns are [down, right, backwards]; OpenCV's [right, down, forward]
    are columns (1, 0, -2) of it."""
    rows = np.load(poses_bounds)
    if len(rows) != len(names):
        raise ValueError(f"{poses_bounds}: {len(rows)} poses for {len(names)} image names")
    out = {}
    for name, row in zip(names, rows):
        m = row[:15].reshape(3, 5)
        c2w = np.eye(4)
        c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = m[:, 1], m[:, 0], -m[:, 2], m[:, 3]
        out[name] = c2w
    return out


def break_cameras(rec, names: list[str], how: str):
    """A copy of the pycolmap model ``rec`` with the cameras ``names`` posed wrong on purpose (what
    the checks of eg-process must catch): ``mirrored`` turns each 180 degrees about its own down
    axis (it looks away); ``misplaced`` moves each to twice its distance from the points' median."""
    import pycolmap

    if how not in ("mirrored", "misplaced"):
        raise ValueError(f"how: 'mirrored' or 'misplaced', got {how!r}")
    out = pycolmap.Reconstruction(rec)
    centre = np.median([p.xyz for p in out.points3D.values()], axis=0)
    for im in out.images.values():
        if im.name not in names:
            continue
        R, t = im.cam_from_world().rotation.matrix(), im.cam_from_world().translation
        c = -R.T @ t
        R = np.diag([-1.0, 1.0, -1.0]) @ R if how == "mirrored" else R
        c = c + 2.0 * (c - centre) if how == "misplaced" else c
        out.frame(im.frame_id).rig_from_world = pycolmap.Rigid3d(pycolmap.Rotation3d(R), -R @ c)
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("estimated", type=Path, help="a posed dataset (eg-process's --out) or a COLMAP model")
    parser.add_argument("reference", type=Path, help="a COLMAP model or dataset, a transforms.json or a poses_bounds.npy")
    parser.add_argument("--names-from", type=Path, help="for poses_bounds.npy: the folder of all its images")
    args = parser.parse_args(argv)
    estimated = colmap_cameras(args.estimated)
    if args.reference.suffix == ".json":
        reference = transforms_cameras(args.reference)
    elif args.reference.suffix == ".npy":
        names = sorted(p.name for p in args.names_from.iterdir() if p.is_file())
        reference = llff_cameras(args.reference, names)
    else:
        reference = colmap_cameras(args.reference)
    result = agreement(estimated, reference)
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
