"""What a strategy observes of one rendered training view: :class:`ViewObservation`.

A training step renders one or more views (a batch, or the views of every rank of a
data-parallel run). The pipeline turns each view's render info into one observation
(:func:`observe_render`), gathers the ranks' observations in the order of the global batch, and
hands the strategy that list: one element at batch 1, B for a batch of B views. gsplat's flat
``info`` dict is made from observations only where gsplat compatibility needs it
(``exploregs_plugin/integrations/``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from torch import Tensor

from .errors import StrategyError


@dataclass
class ViewError:
    """Where one training view is still wrong; filled only for a strategy that requires
    ``VIEW_ERRORS`` (guided exploration)."""

    index: int
    """The view's index in the training set."""
    viewmat: Tensor
    """[4, 4] world-to-camera (OpenCV axes)."""
    K: Tensor
    """[3, 3] pinhole intrinsics in pixels."""
    target: Tensor
    """[H, W, 3] the training image (on this step's background)."""
    error: Tensor
    """[H, W] mean over channels of |render - target|."""

    def to(self, device: Any) -> "ViewError":
        """A detached copy on ``device`` (the form that travels between ranks)."""
        return ViewError(self.index, *(t.detach().to(device) for t in (self.viewmat, self.K, self.target, self.error)))


@dataclass
class ViewObservation:
    """One rendered view as the densification statistics read it.

    The gradient of the loss with respect to the view's 2D means (pixels) is on
    ``means2d.grad`` for a view this process rendered (``step_pre_backward`` retains it), or in
    ``means2d_grad`` for one that travelled from another rank (None there when no gradient
    reached the means)."""

    width: int
    height: int
    radii: Tensor
    """[N, 2] int32 screen radii in pixels; 0 where the Gaussian was not drawn."""
    camera_center: Tensor
    """[3] the camera centre in world coordinates (ray perturbation)."""
    means2d: Tensor | None = None
    """[N, 2] the render's 2D means (non-leaf; None for a view rendered by another rank)."""
    means2d_grad: Tensor | None = None
    """[N, 2] dL/d(mean2d) given explicitly (a gathered view); None: read ``means2d.grad``."""
    means2d_absgrad: Tensor | None = None
    """[N, 2] the absolute sums (``ABSOLUTE_GRADIENT``) given explicitly (a gathered view); None:
    read ``means2d.absgrad``."""
    n_cameras: int = 1
    """How many views the loss averages: the gradient carries 1/n_cameras, which the NDC
    statistic undoes (as gsplat does)."""
    downscale: int = 1
    """The coarse-to-fine level's factor: the view was rendered at 1/downscale of its full size
    per side (``width`` and ``height`` are the level's), which the NDC statistic undoes
    (``ndc_gradient_norms``)."""
    visibility: Tensor | None = None
    """[N, 2] each Gaussian's summed alpha T and alpha over the view's pixels
    (``VISIBILITY_STATS``); None when not asked for."""
    error: ViewError | None = None
    """The view's error map (``VIEW_ERRORS``); None when not asked for."""

    @property
    def num_gaussians(self) -> int:
        return int(self.radii.shape[0])

    def visible(self) -> Tensor:
        """[N] bool: the Gaussians the view drew (both radii positive, the 3DGS test)."""
        return (self.radii > 0).all(dim=-1)

    def screen_gradient(self, absolute: bool = False) -> Tensor | None:
        """[N, 2] dL/d(mean2d) in pixels, or None when no gradient reached the 2D means. With
        ``absolute``, the sums over the view's pixels of each pixel's |dL/dx| and |dL/dy| instead
        (AbsGS; the renderer makes them when asked for ``ABSOLUTE_GRADIENT``)."""
        if absolute:
            return self._absolute_gradient()
        if self.means2d is None or self.means2d_grad is not None:
            return self.means2d_grad
        if not self.gradient_kept():
            raise StrategyError(
                "the view's means2d.grad is not retained: call strategy.step_pre_backward(...) before "
                "loss.backward() so the screen-space gradient is kept"
            )
        return _one_camera(self.means2d.grad)

    def _absolute_gradient(self) -> Tensor | None:
        if self.means2d is None or self.means2d_absgrad is not None:
            return self.means2d_absgrad
        sums = getattr(self.means2d, "absgrad", None)
        if sums is None and self.gradient_kept() and self.means2d.grad is None:
            return None  # no gradient reached the means (the backward never came to the renderer)
        if sums is None:
            raise StrategyError(
                "the view's renderer made no absolute gradient sums (means2d.absgrad): render with "
                "RasterSettings(absgrad=True), which eg-train sets for a strategy that requires ABSOLUTE_GRADIENT"
            )
        return _one_camera(sums)

    def has_absolute_gradient(self) -> bool:
        """Whether the view carries the absolute sums (given, or left by its renderer)."""
        return self.means2d_absgrad is not None or (self.means2d is not None and hasattr(self.means2d, "absgrad"))

    def keep_gradient(self, who: str) -> None:
        """Retain the gradient of the render's 2D means (the densification statistic reads it
        after ``loss.backward()``); ``who`` names the strategy in the error."""
        if self.means2d is None:
            raise StrategyError(f"{who} needs the view's means2d for the screen-space gradient statistic")
        if self.means2d.requires_grad:
            self.means2d.retain_grad()

    def gradient_kept(self) -> bool:
        """Whether the gradient of the render's own 2D means is kept (``step_pre_backward``)."""
        return self.means2d is not None and (self.means2d.is_leaf or self.means2d.retains_grad)

    def check_rows(self, n: int) -> None:
        """Raise when the observation was not made from the current set of ``n`` Gaussians."""
        if tuple(self.radii.shape) != (n, 2):
            raise StrategyError(
                f"the view's radii have shape {tuple(self.radii.shape)} but there are {n} Gaussians: the "
                "observation must come from rendering the current Gaussian set"
            )


def _one_camera(t: Tensor | None) -> Tensor | None:
    """[N, 2] from a render's 2D-mean gradient or sums: gsplat's rasterization differentiates a
    [1, N, 2] tensor (one camera)."""
    return t if t is None or t.dim() == 2 else t.reshape(t.shape[-2:])


def observe_render(info: dict[str, Any], n_cameras: int = 1, error: ViewError | None = None,
                   downscale: int = 1) -> ViewObservation:
    """The observation of one view from the info dict of ``exploregs_plugin.rasterizer.rasterize``
    (every backend gives the same keys; ``visibility`` only when the settings asked for it);
    ``downscale``: the coarse-to-fine factor the view was rendered at (1: full size)."""
    return ViewObservation(
        width=int(info["width"]),
        height=int(info["height"]),
        radii=info["radii"],
        camera_center=info["camera_center"],
        means2d=info["means2d"],
        n_cameras=int(n_cameras),
        downscale=int(downscale),
        visibility=info.get("visibility"),
        error=error,
    )


def require_views(views: Any, who: str) -> list[ViewObservation]:
    """``views`` checked to be what strategies receive: a non-empty list of observations."""
    if isinstance(views, list) and views and all(isinstance(v, ViewObservation) for v in views):
        return views
    raise StrategyError(
        f"{who} receives the step's views as a non-empty list of exploregs_plugin.strategies.observation.ViewObservation "
        f"(got {type(views).__name__}); make one from a rasterizer info dict with observe_render(info)"
    )
