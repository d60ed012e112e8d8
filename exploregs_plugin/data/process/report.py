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
                 seconds: dict[str, float], settings: dict) -> dict:
    """The report's fields for the kept model ``rec`` of a capture of ``all_names``."""
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
        "settings": settings,
    }


def write_report(report: dict, out: Path) -> Path:
    path = out / REPORT_NAME
    atomic_write_text(path, json.dumps(report, indent=1) + "\n")
    return path


def summary_lines(report: dict) -> list[str]:
    """The printed summary: counts, quality, seconds per stage, the images that did not register."""
    seconds = ", ".join(f"{stage} {s:.1f} s" for stage, s in report["seconds"].items())
    lines = [
        f"registered {report['registered']} of {report['images_in']} images, {report['points3D']} 3D points, "
        f"mean reprojection error {report['mean_reprojection_error_px']:.2f} px, "
        f"mean track length {report['mean_track_length']:.2f}",
        f"seconds per stage: {seconds}",
    ]
    if report["other_models_registered"]:
        lines.append(f"other (smaller) models kept apart: {report['other_models_registered']} images registered")
    missing = report["not_registered"]
    if missing:
        shown = ", ".join(missing[:10]) + (f" and {len(missing) - 10} more" if len(missing) > 10 else "")
        lines.append(f"not registered: {shown}")
    return lines


def top_view_axes(up: np.ndarray) -> np.ndarray:
    """Two unit vectors [2, 3] spanning the plane perpendicular to ``up`` (the plot's x and y)."""
    up = up / max(float(np.linalg.norm(up)), 1e-12)
    helper = np.array([1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(up, helper)
    e1 /= max(float(np.linalg.norm(e1)), 1e-12)
    return np.stack([e1, np.cross(up, e1)])


def plot_top_view(rec: pycolmap.Reconstruction, path: Path) -> Path:
    """Camera centres with their viewing directions and the 3D points seen from above (the mean
    of the cameras' up directions, -y in OpenCV axes)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    images = [im for im in rec.images.values() if im.has_pose]
    centres = np.array([im.projection_center() for im in images]).reshape(-1, 3)
    looks = np.array([im.viewing_direction() for im in images]).reshape(-1, 3)
    # camera-to-world rotation R^T: its second column is the camera's y (down) in the world
    downs = np.array([im.cam_from_world().rotation.matrix()[1] for im in images]).reshape(-1, 3)
    axes = top_view_axes(-downs.mean(axis=0) if len(downs) else np.array([0.0, 0.0, 1.0]))
    points = np.array([p.xyz for p in rec.points3D.values()]).reshape(-1, 3)
    colors = np.array([p.color for p in rec.points3D.values()]).reshape(-1, 3) / 255.0
    cams2d, pts2d, look2d = centres @ axes.T, points @ axes.T, looks @ axes.T
    fig, ax = plt.subplots(figsize=(7, 7), dpi=110)
    if len(pts2d):
        ax.scatter(pts2d[:, 0], pts2d[:, 1], s=2, c=colors, alpha=0.8, linewidths=0)
    span = np.ptp(cams2d, axis=0).max() if len(cams2d) > 1 else 1.0
    ax.quiver(cams2d[:, 0], cams2d[:, 1], look2d[:, 0], look2d[:, 1], color="crimson",
              angles="xy", scale_units="xy", scale=1.0 / max(0.08 * span, 1e-9), width=0.004)
    ax.scatter(cams2d[:, 0], cams2d[:, 1], s=12, c="crimson", label=f"{len(cams2d)} cameras")
    # frame the cameras and the bulk of the points (a few far outliers would shrink everything)
    shown = np.concatenate([cams2d, np.percentile(pts2d, [2, 98], axis=0)]) if len(pts2d) else cams2d
    low, high = shown.min(axis=0), shown.max(axis=0)
    pad = 0.08 * max(float((high - low).max()), 1e-6)
    ax.set_xlim(low[0] - pad, high[0] + pad)
    ax.set_ylim(low[1] - pad, high[1] + pad)
    ax.set_aspect("equal")
    ax.set_title(f"top view: {len(cams2d)} cameras, {len(points)} points")
    ax.legend(loc="upper right")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path
