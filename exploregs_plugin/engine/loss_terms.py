"""The training loss as a list of terms, each a small object with its weight.

For one training view the pipeline minimises  sum_k term_k(view)  (a batch of B views takes the
mean over its views); the regularisers of the strategy (MCMC's opacity and scale terms) and of
the model (a deformation field's plane smoothness) enter once per step, not per view. A method
chooses its terms through its PipelineConfig (``ssim_lambda``, ``depth_loss_weight``, ...);
a new term is a class with ``__call__(view) -> (weighted loss, logged parts)``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Protocol, Sequence

from torch import Tensor

from exploregs_plugin.model.losses import DepthSpace, depth_l1, photometric_loss


@dataclass(frozen=True)
class ViewLossInput:
    """What a loss term may read about one rendered training view."""

    image: Tensor
    """[H, W, 3] render."""
    target: Tensor
    """[H, W, 3] training image, on the render's background."""
    depth: Tensor
    """[H, W, 1] rendered expected depth."""
    extras: dict[str, Any] = field(default_factory=dict)
    """The dataset's extras of this view (``depth`` maps, ``alpha``, region masks)."""
    index: int = 0
    """The view's index among the training views."""


class LossTerm(Protocol):
    def __call__(self, view: ViewLossInput) -> tuple[Tensor, dict[str, Tensor]]:
        """(weighted scalar loss in the graph, detached parts to log by name)."""


@dataclass(frozen=True)
class PhotometricTerm:
    """3DGS's image loss: (1 - lambda) L1 + lambda (1 - SSIM); logs ``l1`` and ``dssim`` (and the
    view's PSNR, ``VIEW_PSNR``, where the compiled loss computed it in the same pass)."""

    ssim_lambda: float = 0.2

    def __call__(self, view: ViewLossInput) -> tuple[Tensor, dict[str, Tensor]]:
        return photometric_loss(view.image, view.target, self.ssim_lambda)


@dataclass(frozen=True)
class DepthTerm:
    """weight x L1 between the rendered depth and the dataset's depth map (in z or 1/z); logs
    ``depth``."""

    weight: float
    space: DepthSpace = "depth"

    def target(self, view: ViewLossInput) -> Tensor:
        """The depth map the render is compared with [H, W, 1] (an experiment may degrade it:
        ``exploregs_plugin/analysis/depth_degradation.py``)."""
        if "depth" not in view.extras:
            raise ValueError("depth_loss_weight > 0 but the dataset has no depth maps")
        return view.extras["depth"]

    def __call__(self, view: ViewLossInput) -> tuple[Tensor, dict[str, Tensor]]:
        term = depth_l1(view.depth, self.target(view).to(view.depth.device), self.space)
        return self.weight * term, {"depth": term.detach()}


def view_loss(terms: Sequence[LossTerm], view: ViewLossInput) -> tuple[Tensor, dict[str, Tensor]]:
    """The sum of the terms on one view (in their order) and every term's logged parts."""
    if not terms:
        raise ValueError("the training loss needs at least one term")
    loss, parts = None, {}
    for term in terms:
        value, logged = term(view)
        loss = value if loss is None else loss + value
        parts.update(logged)
    return loss, parts
