"""Synthetic Gaussians, optimizers and the views a strategy observes (``ViewObservation``).

Used by the strategy tests and handy for third-party strategy authors: every strategy can be
exercised without a renderer by feeding it a synthetic screen-space gradient.
"""

from __future__ import annotations

import torch
from torch import Tensor

from .observation import ViewObservation
from .row_ops import Params


def make_gaussians(
    n: int,
    generator: torch.Generator,
    sh_degree: int = 1,
    extent: float = 1.0,
    dtype: torch.dtype = torch.float32,
) -> torch.nn.ParameterDict:
    """Random raw Gaussian parameters in the project's layout.

    means [n, 3] in [-extent, extent]^3, scales [n, 3] log std around 0.02 x extent, quats [n, 4],
    opacities [n] logits, sh0 [n, 1, 3], shN [n, (sh_degree + 1)^2 - 1, 3].
    """
    if n < 0 or sh_degree < 0:
        raise ValueError(f"make_gaussians: n and sh_degree must be >= 0, got {n}, {sh_degree}")
    k = (sh_degree + 1) ** 2

    def rand(*shape: int) -> Tensor:
        return torch.rand(*shape, generator=generator, dtype=dtype)

    def randn(*shape: int) -> Tensor:
        return torch.randn(*shape, generator=generator, dtype=dtype)

    log_extent = torch.log(torch.tensor(extent, dtype=dtype))
    return torch.nn.ParameterDict(
        {
            "means": torch.nn.Parameter((rand(n, 3) * 2 - 1) * extent),
            "scales": torch.nn.Parameter(log_extent + torch.log(torch.tensor(0.02, dtype=dtype)) + 0.5 * randn(n, 3)),
            "quats": torch.nn.Parameter(randn(n, 4)),
            "opacities": torch.nn.Parameter(randn(n)),
            "sh0": torch.nn.Parameter(randn(n, 1, 3) * 0.5),
            "shN": torch.nn.Parameter(randn(n, k - 1, 3) * 0.1),
        }
    )


def make_optimizers(params: Params, lr: float = 1e-3) -> dict[str, torch.optim.Adam]:
    """One Adam per parameter (eps 1e-15), the project's optimizer convention."""
    return {name: torch.optim.Adam([p], lr=lr, eps=1e-15) for name, p in params.items()}


def adam_steps(
    params: Params, optimizers: dict[str, torch.optim.Optimizer], generator: torch.Generator, steps: int = 2
) -> None:
    """Take a few Adam steps with random gradients so every moment is non-zero."""
    for _ in range(steps):
        for name, p in params.items():
            p.grad = torch.randn(p.shape, generator=generator, dtype=p.dtype)
            optimizers[name].step()
            p.grad = None


def synthetic_views(
    pixel_grads: Tensor, visible: Tensor, width: int, height: int, camera_center: Tensor | None = None,
    weights: Tensor | None = None,
) -> list[ViewObservation]:
    """A step's views as the pipeline gives them to a strategy: one observation whose
    ``means2d.grad`` is ``pixel_grads``.

    pixel_grads: [N, 2] dL/d(mean2d) in pixels; visible: [N] bool (radii are 3 where visible);
    weights: [N] each Gaussian's compositing weight summed over the view's pixels (the view's
    ``visibility`` [N, 3]: alpha summed as the same, and a peak weight of 1 where the weight is
    positive, so that the cuts' weight x peak orders the rows as the weight does), None for a view
    without them.
    """
    n = pixel_grads.shape[0]
    means2d = torch.zeros(n, 2, requires_grad=True)
    means2d.grad = pixel_grads.clone()
    radii = torch.where(visible, 3, 0).to(torch.int32).unsqueeze(-1).expand(n, 2).contiguous()
    center = torch.zeros(3) if camera_center is None else camera_center
    visibility = None if weights is None else \
        torch.stack([weights, weights, (weights > 0).to(weights.dtype)], dim=-1).to(torch.float32)
    return [ViewObservation(width=width, height=height, radii=radii, camera_center=center, means2d=means2d,
                            visibility=visibility)]
