"""The near-side trap measured on a scene with ground-truth depth: who can see the occluded
region, and what the densification statistic does for the Gaussians there.

Five questions, each answered by pure functions below:

1. **Can the training views see it at all?** A surface point seen at pixel p of a view is *seen*
   by another view when it projects inside that view and its camera depth z agrees with that
   view's depth map d to ``tol`` (|d - z| <= tol z, the scene generator's rule for the region
   masks). ``seen_by`` counts this per pixel; a test pixel that no training view sees cannot be
   fitted by any method, only guessed.
2. **Which Gaussians belong to the occluded region?** A Gaussian centre takes the region label of
   the pixel under it in the training views where it lies on the surface (same depth rule); its
   *front views* are those where it is not behind the surface (z <= d (1 + tol)), i.e. where no
   opaque surface hides it.
3. **What does blending leave them?** Per view, the renderer's per-Gaussian sums of the
   compositing weight w = alpha T and of alpha give the mean transmittance in front of the
   Gaussian, T-bar = sum(alpha T) / sum(alpha); the view's screen-space gradient norm (NDC) is the
   densification statistic's summand. Default grows a Gaussian when
   sum_v |g_v| / #views_visible > grow_grad2d; dividing each |g_v| by T-bar_v (floored) gives the
   statistic with the attenuation undone (what occlusion-aware splitting ranks by). A point or
   Gaussian is *hidden* from a view when it projects into it behind a surface (d < z (1 - tol));
   "hidden" Gaussians are behind a surface in most views they project into.
4. **How good is the model compared with the truth made blurry?** ``reference_psnrs`` scores
   predictors built from the ground truth (one colour for the region, k x k box blurs, the truth
   one pixel off) on the same pixels, so a model's PSNR can be read as "about as sharp as".
5. **Does the statistic cancel?** ``gradient_cancellation`` compares |sum_p g_p| (what Default
   accumulates) with sum_p |g_p| over a Gaussian's pixels: a large Gaussian over fine texture has
   parts that point every way and a small net gradient.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch
import torch.nn.functional as F
from torch import Tensor

from exploregs_plugin.rasterizer import RasterSettings
from exploregs_plugin.rasterizer.composite import single_threaded_ops
from exploregs_plugin.strategies.occlusion import mean_transmittance

from .branches import ViewProblem, ndc_gradient_norm

DEPTH_TOLERANCE = 0.02
"""Relative depth agreement under which a point counts as seen (the scene generator's value)."""
T_FLOOR = 0.05
"""Smallest T-bar a gradient is divided by in the compensated statistic (as occlusion-aware splitting)."""
NO_REGION = -1
"""Region of a Gaussian that lies on no surface in any training view."""


# ---------------------------------------------------------------------------- geometry
def unproject(depth: Tensor, K: Tensor, viewmat: Tensor) -> Tensor:
    """World points [H, W, 3] of a z-depth map [H, W] at the pixel centres (u + 0.5, v + 0.5).

    x_cam = z K^-1 (u, v, 1); x_world = R^T (x_cam - t) for viewmat = [R | t].
    """
    h, w = depth.shape
    dtype = depth.dtype
    v, u = torch.meshgrid(torch.arange(h, dtype=dtype) + 0.5, torch.arange(w, dtype=dtype) + 0.5, indexing="ij")
    K = K.to(dtype)
    cam = torch.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], torch.ones_like(u)], -1) * depth[..., None]
    R, t = viewmat[:3, :3].to(dtype), viewmat[:3, 3].to(dtype)
    return (cam - t) @ R  # row-vector form of R^T (x - t)


def project_pixels(points: Tensor, viewmats: Tensor, Ks: Tensor, height: int, width: int
                   ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Project points [M, 3] into V views: (z [V, M] camera depth, column [V, M], row [V, M]
    (the pixel hit, clamped into the image), inside [V, M]: in front of the camera and in the image)."""
    dtype = points.dtype
    R, t = viewmats[:, :3, :3].to(dtype), viewmats[:, :3, 3].to(dtype)
    cam = torch.einsum("vij,mj->vmi", R, points) + t[:, None, :]
    z = cam[..., 2]
    safe_z = torch.where(z > 1e-9, z, torch.ones_like(z))  # guards the division behind the camera
    Ks = Ks.to(dtype)
    u = Ks[:, 0, 0, None] * cam[..., 0] / safe_z + Ks[:, 0, 2, None]
    v = Ks[:, 1, 1, None] * cam[..., 1] / safe_z + Ks[:, 1, 2, None]
    inside = (z > 1e-9) & (u >= 0) & (u < width) & (v >= 0) & (v < height)
    return z, u.floor().clamp(0, width - 1).long(), v.floor().clamp(0, height - 1).long(), inside


def lookup(maps: Tensor, col: Tensor, row: Tensor) -> Tensor:
    """maps [V, H, W] read at per-view pixels col, row [V, M] -> [V, M]."""
    return torch.stack([maps[k][row[k], col[k]] for k in range(len(maps))])


def seen_by(points: Tensor, viewmats: Tensor, Ks: Tensor, depths: Tensor, tol: float = DEPTH_TOLERANCE) -> Tensor:
    """[V, M] bool: view v sees point m (inside it and |d - z| <= tol z)."""
    z, col, row, inside = project_pixels(points, viewmats, Ks, *depths.shape[1:])
    d = lookup(depths.to(points.dtype), col, row)
    return inside & ((d - z).abs() <= tol * z)


def hidden_from(points: Tensor, viewmats: Tensor, Ks: Tensor, depths: Tensor, tol: float = DEPTH_TOLERANCE
                ) -> Tensor:
    """[V, M] bool: point m projects into view v but a surface lies in front of it there
    (d < z (1 - tol)): hidden by an occluder, not outside the frustum."""
    z, col, row, inside = project_pixels(points, viewmats, Ks, *depths.shape[1:])
    d = lookup(depths.to(points.dtype), col, row)
    return inside & (d < (1.0 - tol) * z)


def visibility_histogram(counts: Tensor, edges: tuple[int, ...]) -> list[int]:
    """How many of ``counts`` [M] fall in each bin [edges[i], edges[i+1]) (the last bin is open)."""
    bounds = list(edges) + [math.inf]
    return [int(((counts >= lo) & (counts < hi)).sum()) for lo, hi in zip(bounds[:-1], bounds[1:])]


@dataclass
class GaussianRegions:
    """Per Gaussian [N]: ``region`` (majority label where it lies on the surface, NO_REGION if
    nowhere), ``on_surface`` (training views where it lies on the surface), ``front_views``
    (training views where it is inside and not behind the surface) and ``inside_views``
    (training views whose image it projects into, hidden or not)."""

    region: Tensor
    on_surface: Tensor
    front_views: Tensor
    inside_views: Tensor

    def hidden(self) -> Tensor:
        """[N] bool: behind a surface in most of the views it projects into (occluded, not merely
        outside the other views' frusta)."""
        return 2 * self.front_views < self.inside_views


def gaussian_regions(
    means: Tensor, viewmats: Tensor, Ks: Tensor, depths: Tensor, labels: Tensor, n_labels: int,
    tol: float = DEPTH_TOLERANCE,
) -> GaussianRegions:
    """Region of each Gaussian centre from the training views' depth maps and labels [V, H, W]."""
    z, col, row, inside = project_pixels(means, viewmats, Ks, *depths.shape[1:])
    d = lookup(depths.to(means.dtype), col, row)
    surface = inside & ((d - z).abs() <= tol * z)
    front = inside & (z <= d * (1.0 + tol))
    lab = lookup(labels.long(), col, row)  # [V, N]
    votes = torch.stack([(surface & (lab == r)).sum(0) for r in range(n_labels)], -1)  # [N, R]
    region = torch.where(votes.sum(-1) > 0, votes.argmax(-1), torch.full_like(votes[:, 0], NO_REGION))
    return GaussianRegions(region=region, on_surface=surface.sum(0), front_views=front.sum(0),
                           inside_views=inside.sum(0))


# ---------------------------------------------------------------------------- blending statistics
@dataclass
class ViewStats:
    """One view's per-Gaussian numbers [N]: ``grad`` screen-space gradient norm (NDC),
    ``visible`` (radii > 0, Default's counting rule), ``weight`` sum of alpha T, ``alpha`` sum of alpha."""

    grad: Tensor
    visible: Tensor
    weight: Tensor
    alpha: Tensor


def view_stats(view: ViewProblem) -> ViewStats:
    """Render ``view`` with the visibility sums and back-propagate its loss to the 2D means."""
    settings = replace(view.settings or RasterSettings(), visibility_stats=True)
    probe = replace(view, settings=settings)
    _, image, _, info = probe.render()
    with torch.enable_grad(), single_threaded_ops():
        m2d = info["means2d"]
        (grad,) = torch.autograd.grad(probe.loss_fn(image, probe.target), m2d, allow_unused=True)
    grad = torch.zeros_like(m2d) if grad is None else grad
    camera = view.camera
    vis = info["visibility"].detach()
    return ViewStats(ndc_gradient_norm(grad.detach(), camera.width, camera.height),
                     (info["radii"] > 0).all(-1), vis[:, 0], vis[:, 1])


@dataclass
class Accumulated:
    """Sums over views [N]: ``grad_sum``, ``count`` (views where visible), ``comp_sum`` (|g| / max(T-bar,
    T_FLOOR)), ``weight`` and ``alpha`` (the visibility sums), ``lit`` (views where it was
    composited at some pixel: sum(alpha) > 0)."""

    grad_sum: Tensor
    count: Tensor
    comp_sum: Tensor
    weight: Tensor
    alpha: Tensor
    lit: Tensor

    @property
    def statistic_lit(self) -> Tensor:
        """Mean |g| over the views that composite the Gaussian (hidden views left out of the mean)."""
        return self.grad_sum / self.lit.clamp_min(1.0)

    @property
    def statistic(self) -> Tensor:
        """Default's densification statistic: mean |g| over the views where visible (0 if none)."""
        return self.grad_sum / self.count.clamp_min(1.0)

    @property
    def compensated(self) -> Tensor:
        """The same with each view's |g| divided by that view's T-bar (floored at T_FLOOR)."""
        return self.comp_sum / self.count.clamp_min(1.0)

    @property
    def tbar(self) -> Tensor:
        """T-bar per Gaussian; NaN where it was composited nowhere."""
        return mean_transmittance(self.weight, self.alpha, unseen=math.nan)


def accumulate(stats: list[ViewStats], t_floor: float = T_FLOOR) -> Accumulated:
    """Pool per-view statistics the way Default pools its steps (one view per step)."""
    n = stats[0].grad.shape[0]
    acc = Accumulated(*(torch.zeros(n, dtype=torch.float64) for _ in range(6)))
    for s in stats:
        vis = s.visible
        g = s.grad.to(torch.float64)
        t = mean_transmittance(s.weight.to(torch.float64), s.alpha.to(torch.float64)).clamp_min(t_floor)
        acc.grad_sum += torch.where(vis, g, torch.zeros_like(g))
        acc.comp_sum += torch.where(vis, g / t, torch.zeros_like(g))
        acc.count += vis.to(torch.float64)
        acc.weight += s.weight.to(torch.float64)
        acc.alpha += s.alpha.to(torch.float64)
        acc.lit += (vis & (s.alpha > 0)).to(torch.float64)
    return acc


def class_summary(region: Tensor, acc: Accumulated, threshold: float, scales: Tensor,
                  names: dict[int, str]) -> list[dict[str, float | int | str]]:
    """Per region class: Gaussians, median T-bar, mean statistic, share above ``threshold``
    (plain and compensated), share of the summed statistic, and share of Random Splitting's
    scale weights (the chance that a random split lands in the class). scales: [N, 3] log-scales."""
    stat, comp, lit, tbar = acc.statistic, acc.compensated, acc.statistic_lit, acc.tbar
    size = torch.exp(scales.detach().to(torch.float64)).mean(-1)
    size = torch.where(torch.isfinite(size), size, torch.zeros_like(size))
    total_stat = float(stat.sum()) or 1.0  # guards an all-zero statistic
    total_size = float(size.sum()) or 1.0
    rows = []
    for value, name in names.items():
        m = region == value
        k = int(m.sum())
        t = tbar[m]
        t = t[~torch.isnan(t)]
        rows.append({
            "region": name, "gaussians": k,
            "median_tbar": float(t.median()) if t.numel() else math.nan,
            "mean_statistic": float(stat[m].mean()) if k else math.nan,
            "frac_above": float((stat[m] > threshold).double().mean()) if k else math.nan,
            "frac_above_compensated": float((comp[m] > threshold).double().mean()) if k else math.nan,
            "frac_above_lit": float((lit[m] > threshold).double().mean()) if k else math.nan,
            "mean_lit_views": float(acc.lit[m].mean()) if k else math.nan,
            "mean_visible_views": float(acc.count[m].mean()) if k else math.nan,
            "share_statistic": float(stat[m].sum()) / total_stat,
            "share_split_weight": float(size[m].sum()) / total_size,
        })
    return rows


# ---------------------------------------------------------------------------- error by visibility
def psnr_of(sq_sum: float, count: int) -> float:
    """PSNR (dB, images in [0, 1]) of ``count`` squared-error values summing to ``sq_sum``; inf
    for a perfect fit (a ceiling of the analysis, not capped as the evaluation's pooled_psnr is)."""
    if count <= 0:
        return math.nan
    mse = sq_sum / count
    return 10.0 * math.log10(1.0 / mse) if mse > 0 else math.inf


def error_by_visibility(sq: Tensor, counts: Tensor, edges: tuple[int, ...]) -> list[dict[str, float | int]]:
    """Split a region's squared error by how many training views see each pixel.

    sq: [P] squared error per pixel (mean over the colour channels, as the PSNR's MSE);
    counts: [P] training views seeing the pixel's surface point. Per bin [edges[i], edges[i+1])
    (the last open): pixels, share of the region's pixels and of its squared error, the bin's
    PSNR, and the region's PSNR if every pixel of this bin and all *higher* bins were exact
    (the ceiling of a method that fits everything seen by at least edges[i] views).
    """
    total_sq, total_n = float(sq.double().sum()), int(sq.numel())
    bounds = list(edges) + [math.inf]
    rows = []
    for lo, hi in zip(bounds[:-1], bounds[1:]):
        m = (counts >= lo) & (counts < hi)
        at_least = counts >= lo
        s, k = float(sq[m].double().sum()), int(m.sum())
        rows.append({
            "views_lo": lo, "views_hi": hi if math.isfinite(hi) else -1, "pixels": k,
            "share_pixels": k / total_n if total_n else math.nan,
            "share_sq_error": s / total_sq if total_sq > 0 else math.nan,
            "psnr": psnr_of(s, k),
            "region_psnr_if_fitted_from_here": psnr_of(total_sq - float(sq[at_least].double().sum()), total_n),
        })
    return rows


# ---------------------------------------------------------------------------- reference predictors
def box_blur(image: Tensor, k: int) -> Tensor:
    """image [H, W, 3] averaged over k x k pixel boxes (edges replicated), k odd."""
    if k < 1 or k % 2 == 0:
        raise ValueError(f"box_blur: k must be odd and >= 1, got {k}")
    x = image.permute(2, 0, 1)[None].to(torch.float64)
    x = F.avg_pool2d(F.pad(x, (k // 2,) * 4, mode="replicate"), k, stride=1)
    return x[0].permute(1, 2, 0)


def reference_psnrs(images: Tensor, masks: Tensor, blurs: tuple[int, ...] = (3, 5, 9)) -> dict[str, float]:
    """PSNR over the masked pixels of predictors made from the ground truth itself, to place a
    model's score: "region_mean" (one colour for the whole region, pooled over views),
    "blur_k" (the truth box-blurred over k x k pixels) and "shift_1px" (the truth moved one pixel
    sideways: exact texture, misregistered by a pixel). images: [V, H, W, 3]; masks: [V, H, W]."""
    n = int(masks.sum())
    gt = images.to(torch.float64)
    out = {}
    mean = gt[masks].mean(0) if n else torch.zeros(3, dtype=torch.float64)
    out["region_mean"] = psnr_of(float(((gt[masks] - mean) ** 2).mean(-1).sum()), n)
    for k in blurs:
        sq = sum(float(((box_blur(g, k) - g) ** 2).mean(-1)[m].sum()) for g, m in zip(gt, masks))
        out[f"blur_{k}"] = psnr_of(sq, n)
    sq = sum(float(((torch.roll(g, 1, dims=1) - g) ** 2).mean(-1)[m].sum()) for g, m in zip(gt, masks))
    out["shift_1px"] = psnr_of(sq, n)
    return out


# ---------------------------------------------------------------------------- cancellation
def gradient_cancellation(ids: Tensor, grad_px: Tensor, n: int, width: int, height: int) -> dict[str, Tensor]:
    """Per Gaussian [N], from the per-pixel parts of its screen-space gradient in one view
    (``blending.composited_pairs`` with an image gradient: ids [P], grad_px [P, 2] in pixels):
    "net" = |sum_p g_p| (what densification accumulates), "absolute" = sum_p |g_p| (both NDC),
    "pixels" (where it is blended) and "ratio" = net / absolute (1: all parts agree; near 0: they
    cancel, as over fine texture). NaN ratio where a Gaussian has no gradient in the view."""
    g = grad_px.to(torch.float64)
    net = torch.zeros(n, 2, dtype=torch.float64).index_add_(0, ids, g)
    absolute = torch.zeros(n, dtype=torch.float64).index_add_(0, ids, ndc_gradient_norm(g, width, height))
    net_n = ndc_gradient_norm(net, width, height)
    ratio = torch.where(absolute > 0, net_n / absolute.clamp_min(1e-30), torch.full_like(absolute, math.nan))
    return {"net": net_n, "absolute": absolute, "pixels": torch.bincount(ids, minlength=n), "ratio": ratio}
