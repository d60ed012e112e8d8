"""Alpha blending and the screen-space gradient: per pixel and by depth rank over a view.

Front-to-back compositing C = sum_m T_{m-1} alpha_m c_m with T_{m-1} = prod_{i<m} (1 - alpha_i)
gives dC/dalpha_m = T_{m-1} (c_m - C_{m+1:N}) (C_{m+1:N}: colour behind m seen through T_m), so
every gradient that reaches a Gaussian through its alpha carries the factor T_{m-1}: occluded
Gaussians see a small screen-space gradient and rarely pass the densification threshold.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from exploregs_plugin.cameras import Camera
from exploregs_plugin.model.gaussians import activate_detached
from exploregs_plugin.rasterizer import RasterSettings, trace_pixel
from exploregs_plugin.rasterizer.composite import single_threaded_ops
from exploregs_plugin.rasterizer.projection import project_gaussians
from exploregs_plugin.rasterizer.sh import sh_colors
from exploregs_plugin.rasterizer.trace import blend_pairs, dcolor_dalpha

from .branches import ViewProblem, ndc_gradient_norm

ROW_BAND = 2  # image rows evaluated together in the scene-wide pass (bounds memory)


def screen_gradients(view: ViewProblem, pixel: tuple[int, int] | None = None) -> dict[str, Tensor]:
    """Screen-space gradient norms (NDC units) of every Gaussian for one view.

    "image": of the view's training loss (what the densification statistic accumulates);
    "pixel" (when ``pixel`` = (x, y) is given): the part of that gradient that comes through
    pixel (x, y) alone, so the factor T_{m-1} of each Gaussian composited there is not mixed
    with its other pixels. Both [N].
    """
    _, image, _, info = view.render()
    camera = view.camera
    with torch.enable_grad(), single_threaded_ops():
        m2d = info["means2d"]
        losses = {"image": view.loss_fn(image, view.target)}
        if pixel is not None:
            # the view loss linearised at pixel (x, y): dL/dC_p . C_p, whose gradient is the part
            # of the view-loss gradient that reaches each Gaussian through this pixel alone
            x, y = pixel
            (dl_dc,) = torch.autograd.grad(losses["image"], image, retain_graph=True)
            losses["pixel"] = (dl_dc[y, x].detach() * image[y, x]).sum()
        out = {}
        for name, loss in losses.items():
            (grad,) = torch.autograd.grad(loss, m2d, retain_graph=True, allow_unused=True)
            grad = torch.zeros_like(m2d) if grad is None else grad
            out[name] = ndc_gradient_norm(grad.detach(), camera.width, camera.height)
    return out


def pixel_blending(view: ViewProblem, x: int, y: int) -> dict[str, Tensor]:
    """The Gaussians composited at pixel column ``x``, row ``y``, front to back ([m] each):
    "ids", "depths", "alphas", "T_before", "grad_image" and "grad_pixel" (screen-space gradient
    norms in NDC units, see :func:`screen_gradients`), "dC_dalpha" [m, 3], plus "color" [3] and
    "T_final" []."""
    means, quats, scales, opacities, sh = activate_detached(view.params)
    camera = view.camera
    trace = trace_pixel(
        means, quats, scales, opacities, sh, camera, x, y,
        sh_degree=view.sh_degree, background=view.background, settings=view.settings,
    )  # fmt: skip
    grads = screen_gradients(view, pixel=(x, y))
    ids = trace["ids"]
    return {
        "ids": ids, "depths": trace["depths"], "alphas": trace["alphas"], "T_before": trace["T_before"],
        "grad_image": grads["image"][ids], "grad_pixel": grads["pixel"][ids], "dC_dalpha": trace["dC_dalpha"],
        "color": trace["color"], "T_final": trace["T_final"],
    }  # fmt: skip


def image_gradient(view: ViewProblem) -> Tensor:
    """dL/dC of the view's loss with respect to the rendered image: [H, W, 3]."""
    with torch.no_grad():
        _, image, _, _ = view.render()
    with torch.enable_grad(), single_threaded_ops():
        image = image.detach().requires_grad_(True)
        (grad,) = torch.autograd.grad(view.loss_fn(image, view.target), image)
    return grad


def composited_pairs(
    params: dict[str, Tensor],
    camera: Camera,
    settings: RasterSettings | None = None,
    *,
    sh_degree: int = 0,
    background: Tensor | None = None,
    image_grad: Tensor | None = None,
) -> dict[str, Tensor]:
    """Every (pixel, Gaussian) pair the compositor blends in one view, with its depth rank.

    The same rules as the rasterizer and ``trace_pixel``: the pixel centre inside the support
    box, alpha = min(alpha_max, o exp(power)) >= alpha_min, and the stop once T would fall below
    ``transmittance_min``. Returns flat [P] tensors "pixel" (row-major index y W + x), "ids",
    "rank" (0 = front), "T_before", "alphas".

    With ``image_grad`` = dL/dC [H, W, 3] it also returns "grad_px" [P, 2]: the part of
    dL/d(mean2d) of the Gaussian that comes through this pixel,
    (dL/dC_p . T_{m-1} (c_m - C_{m+1:N})) dalpha_m/d(mean2d), with
    dalpha/d(mean2d) = alpha (a dx + b dy, b dx + c dy) (zero where alpha is clamped at
    alpha_max). Summed over a Gaussian's pixels it is the screen-space gradient (tested).
    """
    settings = settings or RasterSettings()
    means, quats, scales, opacities, sh = activate_detached(params)
    dtype = means.dtype
    width, height = int(camera.width), int(camera.height)
    # many small [P, M] ops: OpenMP barriers cost far more than they save (100x on a busy 2-core box)
    with torch.no_grad(), single_threaded_ops():
        proj = project_gaussians(means, quats, scales, opacities, camera.viewmat.to(dtype), camera.K.to(dtype),
                                 width, height, camera.near, camera.far, settings)  # fmt: skip
        order = torch.nonzero(proj.visible).squeeze(1)
        order = order[torch.argsort(proj.depths[order], stable=True)]
        mx, my = proj.means2d[order, 0], proj.means2d[order, 1]
        a, b, c = proj.conics[order].unbind(-1)
        sx, sy = proj.support[order, 0], proj.support[order, 1]
        opa = proj.opacities[order]
        with_grad = image_grad is not None
        if with_grad:
            rgb = sh_colors(sh[order], means[order], camera.camera_center.to(dtype), sh_degree)
            bg = torch.zeros(3, dtype=dtype) if background is None else background.to(dtype)
            flat_grad = image_grad.reshape(-1, 3).to(dtype)
        keys = ("pixel", "ids", "rank", "T_before", "alphas") + (("grad_px",) if with_grad else ())
        parts: dict[str, list[Tensor]] = {k: [] for k in keys}
        xs = torch.arange(width, dtype=dtype) + 0.5
        for y0 in range(0, height, ROW_BAND):
            y1 = min(height, y0 + ROW_BAND)
            # Gaussians whose support box meets this band of rows, still in depth order.
            sel = torch.nonzero(((my + sy) >= y0 + 0.5) & ((my - sy) <= y1 - 0.5)).squeeze(1)
            if sel.numel() == 0:
                continue
            ys = torch.arange(y0, y1, dtype=dtype) + 0.5
            dx = xs.repeat(y1 - y0)[:, None] - mx[sel]  # [P, M]
            dy = ys.repeat_interleave(width)[:, None] - my[sel]
            power = -0.5 * (a[sel] * dx * dx + c[sel] * dy * dy) - b[sel] * dx * dy
            in_box = (dx.abs() <= sx[sel]) & (dy.abs() <= sy[sel])
            raw, alpha, keep, before, t_final = blend_pairs(power, opa[sel], in_box, settings)
            rank = torch.cumsum(keep.to(torch.int64), dim=1) - 1
            p_idx, g_idx = torch.nonzero(keep, as_tuple=True)
            parts["pixel"].append(p_idx + y0 * width)
            parts["ids"].append(order[sel[g_idx]])
            parts["rank"].append(rank[p_idx, g_idx])
            parts["T_before"].append(before[p_idx, g_idx])
            parts["alphas"].append(alpha[p_idx, g_idx])
            if with_grad:
                dl_dc = flat_grad[y0 * width : y1 * width]  # [P, 3]
                # g . dC/dalpha [P, M]: the rule is linear in the colours, so it takes g . c_m
                ds = dcolor_dalpha(alpha, before, t_final, (dl_dc @ rgb[sel].T)[..., None], (dl_dc @ bg)[:, None])[..., 0]
                free = (raw < settings.alpha_max).to(dtype)  # the clamp passes no gradient
                scale = ds * alpha * free
                grad_x = scale * (a[sel] * dx + b[sel] * dy)
                grad_y = scale * (b[sel] * dx + c[sel] * dy)
                parts["grad_px"].append(torch.stack([grad_x[p_idx, g_idx], grad_y[p_idx, g_idx]], -1))
    out = {}
    for key, chunks in parts.items():
        if chunks:
            out[key] = torch.cat(chunks)
        else:
            shape = (0, 2) if key == "grad_px" else (0,)
            out[key] = torch.zeros(shape, dtype=dtype if key in ("T_before", "alphas", "grad_px") else torch.long)
    return out


def blending_by_rank(
    pairs: dict[str, Tensor],
    grad_ndc: Tensor,
    threshold: float | None = None,
    max_rank: int | None = None,
    image_size: tuple[int, int] | None = None,
) -> dict[str, Tensor]:
    """Means over all pixels of a view by depth rank k (0 = the front Gaussian at a pixel).

    pairs: from :func:`composited_pairs`; grad_ndc: [N] screen-space gradient norm per Gaussian;
    image_size: (width, height), needed for the NDC scale of "grad_px".
    Returns [R] tensors "rank", "pixels" (pixels with a k-th Gaussian), "mean_grad",
    "mean_T", with ``threshold`` "frac_above" (share of those Gaussians above it), and when the
    pairs carry "grad_px", "mean_pixel_grad": the mean NDC norm of the gradient that the k-th
    Gaussian receives through that one pixel.
    """
    ranks = pairs["rank"]
    n_rank = int(ranks.max()) + 1 if ranks.numel() else 0
    if max_rank is not None:
        n_rank = min(n_rank, max_rank)
    keep = ranks < n_rank
    ranks = ranks[keep]
    grads = grad_ndc.to(torch.float64)[pairs["ids"][keep]]
    t_before = pairs["T_before"][keep].to(torch.float64)
    count = torch.zeros(n_rank, dtype=torch.float64).index_add_(0, ranks, torch.ones_like(grads))
    safe = count.clamp_min(1.0)  # every listed rank has >= 1 pixel; the clamp only guards division
    out = {
        "rank": torch.arange(n_rank),
        "pixels": count.to(torch.int64),
        "mean_grad": torch.zeros(n_rank, dtype=torch.float64).index_add_(0, ranks, grads) / safe,
        "mean_T": torch.zeros(n_rank, dtype=torch.float64).index_add_(0, ranks, t_before) / safe,
    }
    if "grad_px" in pairs:
        if image_size is None:
            raise ValueError("blending_by_rank: pairs with 'grad_px' need image_size=(width, height)")
        width, height = image_size
        pixel_grads = ndc_gradient_norm(pairs["grad_px"][keep].to(torch.float64), width, height)
        out["mean_pixel_grad"] = torch.zeros(n_rank, dtype=torch.float64).index_add_(0, ranks, pixel_grads) / safe
    if threshold is not None:
        above = (grads > threshold).to(torch.float64)
        out["frac_above"] = torch.zeros(n_rank, dtype=torch.float64).index_add_(0, ranks, above) / safe
    return out


VISIBILITY_EDGES = (0.0, 1e-3, 1e-2, 0.1, 0.5, 1.0 + 1e-9)
"""Bins of a Gaussian's best transmittance in a view (the last edge includes T = 1)."""


def blending_by_visibility(
    pairs: dict[str, Tensor],
    grad_ndc: Tensor,
    threshold: float,
    edges: tuple[float, ...] = VISIBILITY_EDGES,
) -> dict[str, Tensor]:
    """Per Gaussian, its best visibility in the view: the largest T_before over the pixels where
    it is blended (a Gaussian behind others everywhere has a small one). Gaussians are binned by
    it; per bin [B]: "lo", "hi", "gaussians", "mean_grad" (screen-space gradient of the view,
    NDC), "frac_above" (share above ``threshold``).

    pairs: from :func:`composited_pairs`; grad_ndc: [N].
    """
    n = grad_ndc.shape[0]
    best = torch.full((n,), -1.0, dtype=torch.float64)
    best = best.scatter_reduce(0, pairs["ids"], pairs["T_before"].to(torch.float64), reduce="amax")
    blended = best >= 0  # Gaussians not blended at any pixel of this view have no visibility
    grads = grad_ndc.to(torch.float64)
    lo, hi, count, mean, above = [], [], [], [], []
    for a, b in zip(edges[:-1], edges[1:]):
        inside = blended & (best >= a) & (best < b)
        k = int(inside.sum())
        lo.append(a)
        hi.append(min(b, 1.0))
        count.append(k)
        mean.append(float(grads[inside].mean()) if k else math.nan)
        above.append(float((grads[inside] > threshold).double().mean()) if k else math.nan)
    return {"lo": torch.tensor(lo, dtype=torch.float64), "hi": torch.tensor(hi, dtype=torch.float64),
            "gaussians": torch.tensor(count), "mean_grad": torch.tensor(mean, dtype=torch.float64),
            "frac_above": torch.tensor(above, dtype=torch.float64)}  # fmt: skip
