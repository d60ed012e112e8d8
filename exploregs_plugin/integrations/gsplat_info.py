"""gsplat's render ``info`` and our ``ViewObservation``, converted both ways.

Every conversion between the dict gsplat's strategies read and what our strategies observe of a
view is here: :func:`observations` (gsplat's info -> our views, for our operators inside gsplat's
trainers, :mod:`.into_gsplat`) and :func:`gsplat_info` (our views -> gsplat's info, for gsplat's
strategies inside eg-train, :mod:`.from_gsplat`). Pure torch: the module imports without gsplat.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch
from torch import Tensor

from ..strategies.errors import StrategyError
from ..strategies.observation import ViewObservation

CAMERA_KEYS: tuple[str, ...] = ("camera_center", "camtoworlds", "viewmats")
"""Keys of ``info`` the views' camera centres are read from, in this order: ``camera_center`` [3]
or [V, 3] (our renderer's info), ``camtoworlds`` [..., C, 4, 4] (simple_trainer's name for the
training cameras), ``viewmats`` [..., C, 4, 4] (world-to-camera, the argument of gsplat's
rasterization). gsplat's own info carries none of them."""

NO_CAMERA = (
    "ray noise needs the training camera in info: set info['camtoworlds'] = camtoworlds [C, 4, 4] "
    "(or info['viewmats'] [C, 4, 4], or info['camera_center'] [3]) after rendering; gsplat's info has no camera"
)


# ---------------------------------------------------------------------------- gsplat -> ours
def radii_layout(radii: Tensor, packed: bool, pairs: bool) -> Tensor:
    """``radii`` in the layout a gsplat version reads: pairs ([C, N, 2] / packed [nnz, 2]) when
    ``pairs``, else one radius ([C, N] / packed [nnz]).

    A renderer and a strategy of different gsplat versions would otherwise disagree (gsplat 1.5's
    strategy reads ``(radii > 0).all(-1)`` and fails on [C, N]). The conversions keep what both
    versions read: a Gaussian is visible when its radius pair is positive on both axes, and its
    screen size is the larger one; one radius becomes the pair (r, r), a pair becomes its larger
    value where both are positive, else 0.
    """
    dims = (1, 2) if packed else (2, 3)
    if radii.dim() not in dims or (radii.dim() == dims[1] and radii.shape[-1] != 2):
        layouts = "[nnz] or [nnz, 2]" if packed else "[C, N] or [C, N, 2]"
        raise StrategyError(f"info['radii'] has shape {tuple(radii.shape)}; expected {layouts} (packed={packed})")
    has_pairs = radii.dim() == dims[1]
    if has_pairs == pairs:
        return radii
    if pairs:
        return radii.unsqueeze(-1).expand(*radii.shape, 2)
    return torch.where((radii > 0).all(dim=-1), radii.max(dim=-1).values, torch.zeros_like(radii[..., 0]))


def camera_centers(info: Mapping[str, Any]) -> Tensor | None:
    """Each view's camera centre [V, 3] in world coordinates, from the first of
    :data:`CAMERA_KEYS` that ``info`` holds; None when it holds none.

    camera-to-world M = [R | c]: the centre is its translation column c (whatever the axis
    convention, OpenCV or nerfstudio's OpenGL). World-to-camera V = [R | t] maps c to the origin,
    R c + t = 0, so c = -R^T t (R is a rotation: R^-1 = R^T, no inverse to guard), computed per
    view as ``Camera.camera_center`` does, so the centres have its bits.
    """
    for key in CAMERA_KEYS:
        value = info.get(key)
        if value is None:
            continue
        if key == "camera_center":
            return value.reshape(-1, 3)
        if value.dim() < 2 or value.shape[-2:] != (4, 4):
            raise StrategyError(f"info['{key}'] must be [..., C, 4, 4], got {tuple(value.shape)}")
        mats = value.reshape(-1, 4, 4)
        if key == "camtoworlds":
            return mats[:, :3, 3]
        return torch.stack([-(m[:3, :3].transpose(0, 1) @ m[:3, 3]) for m in mats])
    return None


def observations(info: Mapping[str, Any], n: int, packed: bool = False, key_for_gradient: str = "means2d",
                 need_camera: bool = False) -> list[ViewObservation]:
    """Our observations of the views of one gsplat render: one :class:`ViewObservation` per
    image (``n_batches`` x ``n_cameras`` of them), in the order of gsplat's leading dimensions.

    Each has the view's radii as pairs [N, 2] (:func:`radii_layout`; a packed render's [nnz]
    entries are scattered to their ``camera_ids`` / ``gaussian_ids``, 0 for the Gaussians it did not
    draw), the gradient of ``info[key_for_gradient]`` as ``means2d_grad`` [N, 2] (None when none
    reached it), gsplat's ``width``, ``height`` and ``n_cameras`` (the loss's mean over the C
    images, which the gradient carries), and the camera centre from :func:`camera_centers`. A
    render without a camera gets NaN centres, so that nothing reads a made-up camera; with
    ``need_camera`` (ray noise reads it) it fails in one line instead.
    """
    for key in ("radii", "width", "height", "n_cameras"):
        if key not in info:
            raise StrategyError(f"gsplat's info lacks '{key}', which the observations read (keys: {sorted(info)})")
    width, height, n_cameras = int(info["width"]), int(info["height"]), int(info["n_cameras"])
    radii = radii_layout(info["radii"], packed, pairs=True)
    means2d = info.get(key_for_gradient)
    # kept only where step_pre_backward asked for it (DefaultStrategy's); MCMC's reads no gradient
    kept = means2d is not None and (means2d.is_leaf or means2d.retains_grad)
    grad = means2d.grad if kept else None
    if packed:
        n_views = int(info.get("n_batches") or 1) * n_cameras
        image = info["camera_ids"]
        if info.get("batch_ids") is not None:  # gsplat's leading batch dimensions, flattened
            image = info["batch_ids"] * n_cameras + image
        rows = (image, info["gaussian_ids"])
        full = radii.new_zeros(n_views, n, 2)
        full[rows] = radii
        radii = full
        if grad is not None:
            full_grad = grad.new_zeros(n_views, n, 2)
            full_grad[rows] = grad.reshape(-1, 2)
            grad = full_grad
    radii = radii.reshape(-1, n, 2)
    grad = None if grad is None else grad.reshape(-1, n, 2)
    n_views = radii.shape[0]
    centers = camera_centers(info)
    if centers is None:
        if need_camera:
            raise StrategyError(NO_CAMERA)
        centers = torch.full((n_views, 3), float("nan"), device=radii.device)
    elif centers.shape[0] not in (1, n_views):
        raise StrategyError(f"info has {centers.shape[0]} cameras for {n_views} rendered views")
    return [
        ViewObservation(width=width, height=height, radii=radii[v], camera_center=centers[min(v, centers.shape[0] - 1)],
                        means2d_grad=None if grad is None else grad[v].detach(), n_cameras=n_cameras)
        for v in range(n_views)
    ]


# ---------------------------------------------------------------------------- ours -> gsplat
def gsplat_info(views: list[ViewObservation]) -> dict[str, Any]:
    """The ``info`` dict gsplat 1.5.3's DefaultStrategy reads, made from the step's views (one per
    view of the global batch).

    gsplat reads, unpacked: ``means2d.grad`` [C, N, 2] in pixels, ``radii`` [C, N, 2] (a Gaussian
    counts in a view where both are > 0; with ``refine_scale2d_stop_iter`` > 0 its screen size is
    max(radii) / max(width, height)), ``width``, ``height``, ``n_cameras`` and ``gaussian_ids``
    (None unpacked). It normalises each gradient to NDC as
        g_ndc = (g_x * width / 2 * n_cameras, g_y * height / 2 * n_cameras)
    with one width, height and n_cameras for all C views. Our views may differ in size and carry
    their own n_cameras (the number of views whose mean loss made the gradient), so view v's
    gradient is handed over as g_v * (W_v n_v / (W_0 n_0), H_v n_v / (H_0 n_0)) with view 0's
    values in the dict: gsplat then computes exactly g_v * (W_v / 2, H_v / 2) * n_v, our Default's
    statistic (factor 1 when the views agree, the common case, so the bits are the same). Radii
    are scaled by max(W_0, H_0) / max(W_v, H_v) for the same reason. A view whose 2D means got
    no gradient contributes zeros (gsplat needs a tensor). Views that carry the absolute gradient
    sums (``ABSOLUTE_GRADIENT``) hand them over as ``means2d.absgrad``, scaled alike (gsplat's
    ``absgrad`` reads them there)."""
    if not views:
        raise StrategyError("gsplat_info needs the step's views (a non-empty list)")
    first = views[0]
    n = first.num_gaussians
    device = first.radii.device
    ref = torch.tensor([float(first.width), float(first.height)], dtype=torch.float64) * float(first.n_cameras)
    ref_size = float(max(first.width, first.height))
    grads, radii, sums = [], [], []
    absolute = all(view.has_absolute_gradient() for view in views)
    for view in views:
        view.check_rows(n)
        grad = view.screen_gradient()
        grad = torch.zeros(n, 2, device=device) if grad is None else grad.detach().reshape(n, 2).to(torch.float32)
        own = torch.tensor([float(view.width), float(view.height)], dtype=torch.float64) * float(view.n_cameras)
        # ref > 0: image sizes and n_cameras are positive integers.
        factor = (own / ref.clamp_min(1.0)).to(torch.float32).to(device)
        grads.append(grad * factor)
        if absolute:
            total = view.screen_gradient(absolute=True)
            total = torch.zeros(n, 2, device=device) if total is None else total.detach().reshape(n, 2).to(torch.float32)
            sums.append(total * factor)
        size_factor = ref_size / max(float(max(view.width, view.height)), 1.0)
        radii.append(view.radii.detach().to(torch.float32) * size_factor)
    means2d = torch.zeros(len(views), n, 2, device=device)  # only a carrier of the gradient
    means2d.grad = torch.stack(grads)
    if absolute:
        means2d.absgrad = torch.stack(sums)
    return {
        "means2d": means2d,
        "radii": torch.stack(radii),
        "width": int(first.width),
        "height": int(first.height),
        "n_cameras": int(first.n_cameras),
        "gaussian_ids": None,
    }
