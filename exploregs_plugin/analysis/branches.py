"""Per-path gradients of the 3D means: projected 2D mean, 2D covariance, SH view direction.

The rasterizer lets each of the three paths through which a 3D mean reaches the image carry its
own tensor (``means`` -> 2D mean and depth, ``means_cov`` -> covariance through the perspective
Jacobian, ``means_sh`` -> SH view direction). Feeding three leaf copies of the same means and
back-propagating one loss gives each branch's gradient; by the chain rule their sum is the
ordinary gradient dL/dmu = g_mean2d + g_cov + g_sh.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import torch
from torch import Tensor

from exploregs_plugin.cameras import Camera
from exploregs_plugin.model.gaussians import activate_detached
from exploregs_plugin.model.losses import photometric_loss
from exploregs_plugin.rasterizer import RasterSettings, rasterize_branched
from exploregs_plugin.rasterizer.composite import single_threaded_ops

BRANCHES = ("mean2d", "cov", "sh")
"""Names of the three position paths (the same names as ``BranchAblationModelConfig.detach_paths``)."""
CURVES = BRANCHES + ("total",)
NORM_FLOOR = 1e-30  # guards |g| in cosines and ratios


@dataclass
class BranchGradients:
    """Gradients of one view's loss with respect to each path's copy of the means.

    mean2d, cov, sh, total: [N, 3]; visible: [N] bool; means2d_grad: [N, 2] dL/d(mean2d) in
    pixels (the screen-space gradient); camera_center: [3]; width, height: the image size.
    """

    mean2d: Tensor
    cov: Tensor
    sh: Tensor
    total: Tensor
    visible: Tensor
    means2d_grad: Tensor
    camera_center: Tensor
    width: int
    height: int

    def branch(self, name: str) -> Tensor:
        if name not in CURVES:
            raise ValueError(f"unknown gradient branch {name!r}; choose from {', '.join(CURVES)}")
        return getattr(self, name)


LossFn = Callable[[Tensor, Tensor], Tensor]


def check_target(target: Tensor, camera: Camera) -> None:
    if tuple(target.shape) != (camera.height, camera.width, 3):
        raise ValueError(f"target image has shape {tuple(target.shape)}, the camera renders "
                         f"[{camera.height}, {camera.width}, 3]")


def training_loss(ssim_lambda: float) -> LossFn:
    """The photometric training loss (1 - l) L1 + l (1 - SSIM) as a function (image, target) -> []."""
    return lambda image, target: photometric_loss(image, target, ssim_lambda)[0]


@dataclass(frozen=True)
class ViewProblem:
    """One view's loss, everything a gradient probe needs: raw parameters, the camera, the
    target image [H, W, 3], the active SH degree, loss_fn(image, target) -> [], the background
    [3] (None = black) and the raster settings (None = defaults)."""

    params: dict[str, Tensor]
    camera: Camera
    target: Tensor
    sh_degree: int
    loss_fn: LossFn
    background: Tensor | None = None
    settings: RasterSettings | None = None

    def __post_init__(self) -> None:
        check_target(self.target, self.camera)

    def render(self) -> tuple[tuple[Tensor, Tensor, Tensor], Tensor, Tensor, dict]:
        """:func:`render_branches` of this view."""
        return render_branches(self.params, self.camera, self.sh_degree, self.background, self.settings)


def render_branches(
    params: dict[str, Tensor],
    camera: Camera,
    sh_degree: int,
    background: Tensor | None = None,
    settings: RasterSettings | None = None,
) -> tuple[tuple[Tensor, Tensor, Tensor], Tensor, Tensor, dict]:
    """Render with three leaf copies of ``params["means"]``, one per path.

    Returns ((m_mean2d, m_cov, m_sh) leaves [N, 3] requiring grad, image [H, W, 3],
    depth [H, W, 1], info). The other parameters are detached: only the means' paths are measured.
    """
    means, quats, scales, opacities, sh = activate_detached(params)
    leaves = tuple(means.clone().requires_grad_(True) for _ in BRANCHES)
    with torch.enable_grad():
        image, _, depth, info = rasterize_branched(
            leaves[0], quats, scales, opacities, sh, camera,
            sh_degree=sh_degree, background=background, means_cov=leaves[1], means_sh=leaves[2],
            settings=settings,
        )  # fmt: skip
    return leaves, image, depth, info


def branch_gradients(view: ViewProblem) -> BranchGradients:
    """One view's loss gradient through each path.

    ``total`` is the sum of the three branches, which equals the single-tensor gradient (tested).
    """
    leaves, image, _, info = view.render()
    # the loss (SSIM convolutions) on one small image: single-threaded ops avoid OpenMP barrier waits
    with torch.enable_grad(), single_threaded_ops():
        info["means2d"].retain_grad()
        view.loss_fn(image, view.target).backward()
    grads = [leaf.grad if leaf.grad is not None else torch.zeros_like(leaf) for leaf in leaves]
    g2d = info["means2d"].grad
    camera = view.camera
    return BranchGradients(
        mean2d=grads[0], cov=grads[1], sh=grads[2], total=grads[0] + grads[1] + grads[2],
        visible=info["visible"].clone(),
        means2d_grad=g2d if g2d is not None else torch.zeros_like(info["means2d"]).detach(),
        camera_center=info["camera_center"].detach(), width=int(camera.width), height=int(camera.height),
    )  # fmt: skip


def ndc_gradient_norm(pixel_grad: Tensor, width: int, height: int) -> Tensor:
    """|dL/d(mean2d)| in NDC units (pixel gradient x W/2, H/2), the densification statistic.

    pixel_grad: [..., 2] -> [...].
    """
    scale = pixel_grad.new_tensor([width / 2.0, height / 2.0])
    return (pixel_grad * scale).norm(dim=-1)


def branch_norm_means(grads: BranchGradients) -> dict[str, float]:
    """Mean over the visible Gaussians of |g| for each branch and the total (0 when none is visible)."""
    live = grads.visible
    count = int(live.sum())
    out = {}
    for name in CURVES:
        norms = grads.branch(name)[live].norm(dim=-1)
        out[name] = float(norms.sum()) / count if count else 0.0
    return out


def sample_branch_norms(views: list[ViewProblem]) -> dict[str, float]:
    """Per-view mean gradient norms of each branch, averaged over ``views``.

    Per view, because the training step back-propagates one view at a time: the norm of a
    gradient summed over views would cancel the in-plane components of different views.
    """
    if not views:
        raise ValueError("sample_branch_norms needs at least one view")
    totals = dict.fromkeys(CURVES, 0.0)
    for view in views:
        for name, value in branch_norm_means(branch_gradients(view)).items():
            totals[name] += value
    return {name: value / len(views) for name, value in totals.items()}
