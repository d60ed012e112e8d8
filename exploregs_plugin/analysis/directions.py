"""Directions of the branch gradients relative to the viewing ray and the optical axis.

For one view the 2D-mean branch is dL/dmu = (dL/dp)^T dp/dmu with p the pinhole projection; p
does not change along the ray through the camera centre, so dp/dmu annihilates the ray and the
gradient is orthogonal to it (|cos| = 0). The SH direction d = (mu - c)/|mu - c| has the same
property. Only the covariance branch (the Jacobian depends on depth) can point along the ray.
Summed over views the gradient is orthogonal to no single ray, hence single-view passes here.
"""

from __future__ import annotations

from torch import Tensor

from exploregs_plugin.cameras import Camera

from .branches import NORM_FLOOR, BranchGradients

REFERENCES = ("ray", "axis")
"""Reference directions: the camera-to-Gaussian ray and the camera's optical axis."""


def abs_cosine(vectors: Tensor, references: Tensor) -> Tensor:
    """|cos| of the angle between rows. vectors, references: [N, 3] (references broadcastable) -> [N].

    Rows with a (near) zero vector give 0 (callers drop them with :func:`nonzero_rows`).
    """
    dot = (vectors * references).sum(-1).abs()
    norms = vectors.norm(dim=-1) * references.norm(dim=-1)
    return dot / norms.clamp_min(NORM_FLOOR)


def ray_directions(means: Tensor, camera_center: Tensor) -> Tensor:
    """Camera-to-Gaussian directions (unnormalised). means: [N, 3]; camera_center: [3] -> [N, 3]."""
    return means - camera_center


def optical_axis(camera: Camera) -> Tensor:
    """The camera's +z axis in world coordinates: the third row of the world-to-camera rotation. [3]."""
    return camera.viewmat[2, :3]


def nonzero_rows(grads: Tensor, visible: Tensor, rel_floor: float = 1e-6) -> Tensor:
    """Visible rows whose gradient is not negligible: |g| > rel_floor x max |g| (and > 0). [N] bool.

    Gaussians that touch no pixel of the loss have an exactly zero (or round-off) gradient whose
    direction means nothing.
    """
    norms = grads.norm(dim=-1)
    live = visible & (norms > 0)
    if not bool(live.any()):
        return live
    return live & (norms > rel_floor * float(norms[live].max()))


def branch_cosines(grads: BranchGradients, means: Tensor, camera: Camera) -> dict[str, dict[str, Tensor]]:
    """|cos| of each branch's per-Gaussian gradient with the ray and the optical axis.

    means: [N, 3]. Returns {branch: {"ray": [n_b], "axis": [n_b]}} over the Gaussians for which
    that branch's gradient is non-negligible.
    """
    ray = ray_directions(means.detach(), grads.camera_center)
    axis = optical_axis(camera).to(means.dtype).expand_as(ray)
    out: dict[str, dict[str, Tensor]] = {}
    for name in ("mean2d", "cov", "sh", "total"):
        g = grads.branch(name)
        keep = nonzero_rows(g, grads.visible)
        out[name] = {"ray": abs_cosine(g[keep], ray[keep]), "axis": abs_cosine(g[keep], axis[keep])}
    return out
