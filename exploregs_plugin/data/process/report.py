"""What a processing found: ``process_report.json``, the printed summary and a top-view plot of
the camera centres, their viewing directions and the points."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pycolmap

from ...io.atomic import atomic_write_text

REPORT_NAME = "process_report.json"
PLOT_NAME = "process_top_view.png"


def model_report(rec: pycolmap.Reconstruction, all_names: list[str], other_models: list[int],
                 seconds: dict[str, float], settings: dict, model_checks: dict | None = None,
                 left_out: list[str] | None = None, came_back: list[str] | None = None) -> dict:
    """The report's fields for the kept model ``rec`` of a capture of ``all_names``: counts,
    errors, seconds, and what the model's checks found (``checks``; ``left_out``: the suspect
    images removed from the model; ``came_back``: suspect images that registered again into the
    model without them and passed its checks)."""
    registered = {im.name for im in rec.images.values() if im.has_pose}
    return {
        "images_in": len(all_names),
        "registered": len(registered),
        "points3D": rec.num_points3D(),
        "mean_reprojection_error_px": round(float(rec.compute_mean_reprojection_error()), 4),
        "mean_track_length": round(float(rec.compute_mean_track_length()), 3),
        "seconds": {stage: round(s, 2) for stage, s in seconds.items()},
        "not_registered": sorted(set(all_names) - registered),
        "other_models_registered": other_models,
        "checks": model_checks or {},
        "left_out": sorted(left_out or []),
        "came_back": sorted(came_back or []),
        "settings": settings,
    }


def write_report(report: dict, out: Path) -> Path:
    path = out / REPORT_NAME
    atomic_write_text(path, json.dumps(report, indent=1) + "\n")
    return path


def summary_lines(report: dict) -> list[str]:
    """The printed summary: counts, quality, seconds per stage, the images that did not register,
    the model's checks (and what was left out, in a ``warning:`` line)."""
    seconds = ", ".join(f"{stage} {s:.1f} s" for stage, s in report["seconds"].items())
    lines = [
        f"registered {report['registered']} of {report['images_in']} images, {report['points3D']} 3D points, "
        f"mean reprojection error {report['mean_reprojection_error_px']:.2f} px, "
        f"mean track length {report['mean_track_length']:.2f}",
        f"seconds per stage: {seconds}",
    ]
    found = report.get("checks") or {}
    if found:
        mapper = report["settings"].get("mapper", "")
        lines.append(f"model checked ({mapper} mapper): " + ("no image suspect" if found["passed"] else
                     f"{len(found['suspect'])} images suspect") + _check_counts(found))
    if report["other_models_registered"]:
        lines.append(f"other (smaller) models kept apart: {report['other_models_registered']} images registered")
    missing = [n for n in report["not_registered"] if n not in set(report.get("left_out", []))]
    if missing:
        lines.append(f"not registered: {shown_names(missing)}")
    if report.get("came_back"):
        lines.append(f"{len(report['came_back'])} suspect images registered again into the checked model and passed "
                     f"its checks: {shown_names(report['came_back'])}")
    if report.get("left_out"):
        lines.append(f"warning: {len(report['left_out'])} of {report['images_in']} images were posed inconsistently "
                     f"with the rest and are left out of the dataset ({shown_names(report['left_out'])}); the capture "
                     "may hold repeated or symmetric structure: try more photos between those views, --matching "
                     "exhaustive, or the other --mapper")
    return lines


def shown_names(names: list[str], most: int = 10) -> str:
    """The first ``most`` names, then how many more."""
    return ", ".join(names[:most]) + (f" and {len(names) - most} more" if len(names) > most else "")


def _check_counts(found: dict) -> str:
    """' (looks away 0, disagree 0 of 312 pairs checked, jumps 0, weak 2)'."""
    parts = [f"look away {len(found['looks_away'])}" if found["orbit"] else "not an orbit",
             f"disagree {len(found['disagrees'])} ({found['pairs_contradicted']} of {found['pairs_checked']} "
             "strong pairs contradicted)"]
    if found["ordered"]:
        parts.append(f"jumps {len(found['jumps'])}")
        if found.get("seams"):
            parts.append(f"seams {len(found['seams'])}")
        if found.get("gaps"):
            parts.append(f"gaps {len(found['gaps'])} (long steps the matches do not contradict)")
    parts.append(f"weak {len(found['weak'])}")
    return " (" + ", ".join(parts) + ")"


def top_view_axes(up: np.ndarray) -> np.ndarray:
    """Two unit vectors [2, 3] spanning the plane perpendicular to ``up`` (the plot's x and y)."""
    up = up / max(float(np.linalg.norm(up)), 1e-12)
    helper = np.array([1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(up, helper)
    e1 /= max(float(np.linalg.norm(e1)), 1e-12)
    return np.stack([e1, np.cross(up, e1)])


def plot_top_view(rec: pycolmap.Reconstruction, path: Path, suspect: list[str] | None = None) -> Path:
    """Camera centres with their viewing directions and the 3D points seen from above (the mean
    of the cameras' up directions, -y in OpenCV axes); ``suspect`` cameras (the checks' or left
    out, drawn if still in ``rec``) in another colour. The view frames the cameras and the points
    near them: a capture's far background (a wall, the sky) would otherwise shrink the camera ring
    to a smudge (axes of 50 units for a ring of radius 3 on one capture)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    suspect = set(suspect or [])
    images = [im for im in rec.images.values() if im.has_pose]
    centres = np.array([im.projection_center() for im in images]).reshape(-1, 3)
    looks = np.array([im.viewing_direction() for im in images]).reshape(-1, 3)
    # camera-to-world rotation R^T: its second column is the camera's y (down) in the world
    downs = np.array([im.cam_from_world().rotation.matrix()[1] for im in images]).reshape(-1, 3)
    axes = top_view_axes(-downs.mean(axis=0) if len(downs) else np.array([0.0, 0.0, 1.0]))
    points = np.array([p.xyz for p in rec.points3D.values()]).reshape(-1, 3)
    colors = np.array([p.color for p in rec.points3D.values()]).reshape(-1, 3) / 255.0
    cams2d, pts2d, look2d = centres @ axes.T, points @ axes.T, looks @ axes.T
    low, high = frame_of(cams2d, pts2d)
    near = np.all((pts2d >= low) & (pts2d <= high), axis=1) if len(pts2d) else np.zeros(0, bool)
    fig, ax = plt.subplots(figsize=(7, 7), dpi=110)
    if near.any():
        ax.scatter(pts2d[near, 0], pts2d[near, 1], s=2, c=colors[near], alpha=0.8, linewidths=0)
    span = float((high - low).max())
    bad = np.array([im.name in suspect for im in images], dtype=bool)
    for mask, colour, label in ((~bad, "crimson", "cameras"), (bad, "darkorange", "suspect cameras")):
        if mask.any():
            ax.quiver(cams2d[mask, 0], cams2d[mask, 1], look2d[mask, 0], look2d[mask, 1], color=colour,
                      angles="xy", scale_units="xy", scale=1.0 / max(0.06 * span, 1e-9), width=0.004)
            ax.scatter(cams2d[mask, 0], cams2d[mask, 1], s=12, c=colour, label=f"{int(mask.sum())} {label}")
    ax.set_xlim(low[0], high[0])
    ax.set_ylim(low[1], high[1])
    ax.set_aspect("equal")
    hidden = f", {int((~near).sum())} beyond the frame" if len(pts2d) and not near.all() else ""
    ax.set_title(f"top view: {len(cams2d)} cameras, {len(points)} points{hidden}")
    if len(cams2d):
        ax.legend(loc="upper right")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path


def frame_of(cams2d: np.ndarray, pts2d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The plot's square frame (low, high corners): the cameras' box, grown to hold the bulk (2nd
    to 98th percentile) of the points within one camera extent of the cameras' centre, or within
    the median point's distance where that is larger (an orbit's object sits inside the ring; a
    forward capture's scene lies ahead of it), then padded by 8%. Far points stay outside."""
    if len(cams2d) == 0:
        cams2d = pts2d[:1] if len(pts2d) else np.zeros((1, 2))
    centre = 0.5 * (cams2d.min(axis=0) + cams2d.max(axis=0))
    extent = max(float(np.ptp(cams2d, axis=0).max()), 1e-6)
    shown = cams2d
    if len(pts2d):
        distance = np.linalg.norm(pts2d - centre, axis=1)
        close = pts2d[distance <= max(extent, float(np.median(distance)))]
        if len(close):
            shown = np.concatenate([cams2d, np.percentile(close, [2, 98], axis=0)])
    low, high = shown.min(axis=0), shown.max(axis=0)
    mid, half = 0.5 * (low + high), 0.5 * float((high - low).max()) * 1.08 + 1e-6
    return mid - half, mid + half
