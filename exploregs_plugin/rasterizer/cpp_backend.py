"""The compiled CPU renderer (``RasterSettings.backend = "cpp"``): autograd Functions over the
C++ kernels of :mod:`exploregs_plugin.kernels` (projection, SH colours, tile binning and
compositing, each forward and backward). Projection and SH colours fall back to the torch ops
when the branch ablation feeds separate tensors to their paths, or the camera itself needs a
gradient.
"""

from __future__ import annotations

import torch
from torch import Tensor

from exploregs_plugin.kernels import cpp_problem, extension

from .projection import Projected
from .settings import VISIBILITY_COLUMNS, VISIBILITY_PEAK, RasterSettings

__all__ = ["cpp_problem", "CppBins", "composite_cpp", "project_cpp", "sh_colors_cpp"]


def _as_dtype(t: Tensor, dtype: torch.dtype) -> Tensor:
    """``t`` in ``dtype`` (the support is a non-differentiable output: nothing to detach), with no
    operator dispatched where it is in that dtype already."""
    return t if t.dtype == dtype else t.to(dtype)


def _thresholds(s: RasterSettings) -> tuple[float, float, float]:
    return s.alpha_max, s.alpha_min, s.transmittance_min



class CppBins:
    """Tile-Gaussian pairs made by the C++ binning (front to back within each tile) of the rows
    where ``visible`` holds (every row when it is None). Given the rows' ``conics``, ``opacities``
    and the settings' ``alpha_min``, a row takes only the tiles of its support box that hold a
    pixel centre where its alpha may reach ``alpha_min`` (the others would add exact zeros: the
    same image and gradients, fewer pairs); without them, every tile of the box."""

    def __init__(self, means2d: Tensor, support: Tensor, depths: Tensor, width: int, height: int, tile_size: int,
                 visible: Tensor | None = None, conics: Tensor | None = None, opacities: Tensor | None = None,
                 alpha_min: float = 0.0):
        # pairs are made front to back: the kernel sorts the drawn rows by depth (stable, ties by
        # row: the order of torch.argsort(depths, stable=True) restricted to them)
        if visible is None:
            visible = torch.ones(means2d.shape[0], dtype=torch.bool, device=means2d.device)
        # no detach: the binning reads the values only, and records nothing for autograd
        m2, sup = means2d.contiguous(), _as_dtype(support, means2d.dtype).contiguous()
        z = _as_dtype(depths, means2d.dtype).contiguous()
        if conics is not None:
            conics, opacities = conics.contiguous(), opacities.contiguous()
        self.tile_offsets, self.pair_gauss, self.pair_slot, self.gauss_first, self.gauss_count = extension().bin_tiles(
            m2, sup, z, visible.contiguous(), conics, opacities, alpha_min, width, height, tile_size)
        self.width, self.height, self.tile_size = width, height, tile_size

    @property
    def n_pairs(self) -> int:
        return int(self.pair_gauss.numel())


class _CompositeCpp(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, opacities, feats, support, bins, settings, threads):  # type: ignore[override]
        # no detach: a Function's forward runs without grad recording, and each operator a step
        # dispatches costs interpreter time (docs/training.md, "Operators per step")
        tensors = [t.contiguous() for t in (means2d, conics, opacities, feats)]
        sup = _as_dtype(support, means2d.dtype).contiguous()
        ext = extension()
        out, pair_stats = ext.composite_forward(
            *tensors, sup, bins.tile_offsets, bins.pair_gauss, bins.pair_slot, bins.width, bins.height,
            bins.tile_size, *_thresholds(settings), settings.visibility_stats, threads,
        )  # fmt: skip
        if settings.visibility_stats:
            # the columns before the peak are summed over the Gaussian's tiles, the peak is the largest
            visibility = ext.sum_pairs(pair_stats, bins.gauss_first, bins.gauss_count, VISIBILITY_PEAK, threads)
        else:
            visibility = out.new_zeros(0, len(VISIBILITY_COLUMNS))
        ctx.mark_non_differentiable(visibility)
        ctx.save_for_backward(*tensors, sup, out)
        ctx.bins, ctx.settings, ctx.threads = bins, settings, threads
        ctx.means2d = means2d if settings.absgrad else None  # the tensor the caller reads .absgrad of
        return out, visibility

    @staticmethod
    def backward(ctx, grad_out, grad_visibility):  # type: ignore[override]
        means2d, conics, opacities, feats, sup, out = ctx.saved_tensors
        b, s = ctx.bins, ctx.settings
        ext = extension()
        pair_grad = ext.composite_backward(
            means2d, conics, opacities, feats, sup, b.tile_offsets, b.pair_gauss, b.pair_slot, out,
            grad_out.contiguous(), b.width, b.height, b.tile_size, *_thresholds(s), s.absgrad, ctx.threads,
        )  # fmt: skip
        g = ext.sum_pairs(pair_grad, b.gauss_first, b.gauss_count, pair_grad.shape[1], ctx.threads)
        nf = feats.shape[1]
        if ctx.means2d is not None:
            ctx.means2d.absgrad = g[:, 6 + nf:]
        return g[:, 0:2], g[:, 2:5], g[:, 5], g[:, 6:6 + nf], None, None, None, None


def composite_cpp(
    means2d: Tensor, conics: Tensor, opacities: Tensor, feats: Tensor, support: Tensor, bins: CppBins,
    settings: RasterSettings, threads: int,
) -> tuple[Tensor, Tensor]:
    """Composites binned Gaussians: [H, W, F + 1] (features, then the accumulated alpha) and, with
    ``settings.visibility_stats``, [M, 3] per Gaussian: the sums of w = alpha T and of alpha, and
    the largest w (``VISIBILITY_COLUMNS``; else [0, 3])."""
    return _CompositeCpp.apply(means2d, conics, opacities, feats, support, bins, settings, threads)


class _ProjectCpp(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, quats, scales, opacities, viewmat, K, width, height, near, far, settings, threads):  # type: ignore[override]
        inputs = [t.contiguous() for t in (means, quats, scales, opacities)]  # no detach: see _CompositeCpp
        # no detach: the compiled projection is chosen only for a camera without gradient
        camera = (viewmat, K, width, height, float(near), float(far), settings.eps2d,
                  settings.sigma_radius, settings.guard_band, settings.antialiased)  # fmt: skip
        means2d, conics, opac, depths, radii, support, visible = extension().project_forward(*inputs, *camera, settings.alpha_min, threads)
        ctx.mark_non_differentiable(radii, support, visible)
        ctx.save_for_backward(*inputs)
        ctx.camera, ctx.threads = camera, threads
        return means2d, conics, opac, depths, radii, support, visible

    @staticmethod
    def backward(ctx, g_means2d, g_conics, g_opac, g_depths, *_):  # type: ignore[override]
        inputs = ctx.saved_tensors
        n, like = inputs[0].shape[0], inputs[0]
        # the kernel reads strided rows (the compositor's gradients are columns of one block): no copies
        grads = [like.new_zeros(shape) if g is None else g
                 for g, shape in ((g_means2d, (n, 2)), (g_conics, (n, 3)), (g_opac, (n,)), (g_depths, (n,)))]
        d = extension().project_backward(*inputs, *ctx.camera, *grads, ctx.threads)
        return (*d, None, None, None, None, None, None, None, None)


def project_cpp(
    means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, viewmat: Tensor, K: Tensor, width: int,
    height: int, near_plane: float, far_plane: float, settings: RasterSettings, threads: int,
) -> Projected:
    """:func:`projection.project_gaussians` as one compiled kernel (forward and backward), for one
    tensor of means (no separate covariance path) and a camera without gradient."""
    means2d, conics, opac, depths, radii, support, visible = _ProjectCpp.apply(
        means, quats, scales, opacities, viewmat, K, width, height, near_plane, far_plane, settings, threads)
    return Projected(means2d, conics, opac, depths, radii, support, visible)


class _ShCpp(torch.autograd.Function):
    @staticmethod
    def forward(ctx, sh0, shN, means, visible, camera_center, degree, threads):  # type: ignore[override]
        inputs = (sh0.contiguous(), shN.contiguous(), means.contiguous(), visible.contiguous(),
                  camera_center.detach())  # see _CompositeCpp
        ctx.save_for_backward(*inputs)
        ctx.degree, ctx.threads = degree, threads
        return extension().sh_forward(*inputs, degree, threads)

    @staticmethod
    def backward(ctx, g_colors):  # type: ignore[override]
        # strided rows read as they are; each gradient in its parameter's layout (nothing to copy)
        d_sh0, d_shN, d_means = extension().sh_backward(*ctx.saved_tensors, ctx.degree, g_colors, ctx.threads)
        return d_sh0, d_shN, d_means, None, None, None, None


def sh_colors_cpp(coeffs: Tensor | tuple[Tensor, Tensor], means: Tensor, visible: Tensor, camera_center: Tensor,
                  degree: int, threads: int) -> Tensor:
    """:func:`sh.sh_colors` of the coefficients and means [N, 3] where ``visible`` [N] (bool) holds, 0
    in the other rows: [N, 3] (the compositor reads the visible rows of full-size tensors). The
    coefficients are [N, K, 3] or, as the model keeps them, the pair (sh0 [N, 1, 3], shN [N, K - 1,
    3]), read where they are: no concatenation, and each gradient lands in its parameter's layout."""
    sh0, shN = coeffs if isinstance(coeffs, tuple) else (coeffs[:, :1], coeffs[:, 1:])
    return _ShCpp.apply(sh0, shN, means, visible, camera_center, degree, threads)
