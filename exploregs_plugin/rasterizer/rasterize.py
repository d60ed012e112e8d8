"""The public rasterizer: project (autograd) -> bin (one sort) -> composite (custom Function)."""

from __future__ import annotations

import math
import numbers
from typing import Any

import torch
from torch import Tensor

from ..cameras import Camera
from .backends import backend_problem, resolve_backend
from .composite import (composite, enter_single_threaded, exit_single_threaded, single_threaded_now,
                        single_threaded_ops, thread_budget)
from .cpp_backend import CppBins, composite_cpp, project_cpp, sh_colors_cpp
from .gsplat_backend import BackendError, rasterize_gsplat
from .projection import project_gaussians
from .settings import VISIBILITY_COLUMNS, RasterSettings
from .sh import sh_colors
from .tiling import bin_gaussians

# Accumulated alpha below this gives expected depth 0 (guards the division D / A).
ALPHA_DEPTH_MIN = 1e-10


class _SingleThreadedBackward(torch.autograd.Function):
    """Identity on the outputs; in backward it makes the rest of this backward pass run torch
    ops single-threaded (restored by a callback when the pass ends).

    Measured on shared 2-core machines: the projection's backward on [N, ...] tensors is slower
    with OpenMP threads than without (barrier waits), while the compositor's own backward runs
    one worker thread per core regardless of this setting.
    """

    @staticmethod
    def forward(ctx, *tensors):  # type: ignore[override]
        return tuple(t.clone() for t in tensors)

    @staticmethod
    def backward(ctx, *grads):  # type: ignore[override]
        enter_single_threaded()
        torch.autograd.Variable._execution_engine.queue_callback(exit_single_threaded)
        return grads


def _check(name: str, t: Tensor | None, shape: tuple[int | None, ...]) -> None:
    if t is None:
        return
    if not isinstance(t, Tensor):
        raise TypeError(f"rasterize: argument '{name}' must be a torch.Tensor, got {type(t).__name__}")
    if t.dim() != len(shape) or any(s is not None and s != d for s, d in zip(shape, t.shape)):
        want = "[" + ", ".join("N" if s is None else str(s) for s in shape) + "]"
        raise ValueError(f"rasterize: argument '{name}' must have shape {want}, got {list(t.shape)}")


SHCoeffs = Tensor | tuple[Tensor, Tensor]
"""SH coefficients [N, K, 3], or the model's pair (sh0 [N, 1, 3], shN [N, K - 1, 3]), which the
compiled kernels read as they are and the other paths join (:func:`_joined`)."""


def _joined(sh_coeffs: SHCoeffs | None) -> Tensor | None:
    """[N, K, 3]: the pair (sh0, shN) concatenated, a tensor as it is."""
    return torch.cat(sh_coeffs, dim=1) if isinstance(sh_coeffs, tuple) else sh_coeffs


def _validate(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    sh_coeffs: SHCoeffs | None,
    colors: Tensor | None,
    viewmat: Tensor,
    K: Tensor,
    width: int,
    height: int,
    sh_degree: int | None,
    means_cov: Tensor | None,
    means_sh: Tensor | None,
    background: Tensor | None,
) -> int:
    """Checks shapes and returns the active SH degree (-1 when ``colors`` are given)."""
    _check("means", means, (None, 3))
    n = means.shape[0]
    _check("quats", quats, (n, 4))
    _check("scales", scales, (n, 3))
    _check("opacities", opacities, (n,))
    _check("viewmat", viewmat, (4, 4))
    _check("K", K, (3, 3))
    _check("means_cov", means_cov, (n, 3))
    _check("means_sh", means_sh, (n, 3))
    _check("background", background, (3,))
    integral = isinstance(width, numbers.Integral) and isinstance(height, numbers.Integral)
    if not integral or width < 1 or height < 1:
        raise ValueError(f"rasterize: width and height must be positive ints, got {width!r}, {height!r}")
    if (sh_coeffs is None) == (colors is None):
        raise ValueError("rasterize: give exactly one of 'sh_coeffs' [N, K, 3] and 'colors' [N, 3]")
    if colors is not None:
        _check("colors", colors, (n, 3))
        return -1
    if isinstance(sh_coeffs, tuple):
        if len(sh_coeffs) != 2:
            raise ValueError("rasterize: 'sh_coeffs' as a tuple is the pair (sh0 [N, 1, 3], shN [N, K - 1, 3])")
        _check("sh_coeffs[0] (sh0)", sh_coeffs[0], (n, 1, 3))
        _check("sh_coeffs[1] (shN)", sh_coeffs[1], (n, None, 3))
        n_coeffs = 1 + sh_coeffs[1].shape[1]
    else:
        _check("sh_coeffs", sh_coeffs, (n, None, 3))
        n_coeffs = sh_coeffs.shape[1]
    full = math.isqrt(n_coeffs) - 1
    if (full + 1) ** 2 != n_coeffs or full > 3:
        raise ValueError(f"rasterize: sh_coeffs must have 1, 4, 9 or 16 coefficients per Gaussian, got {n_coeffs}")
    degree = full if sh_degree is None else sh_degree
    if not 0 <= degree <= full:
        raise ValueError(f"rasterize: sh_degree must be in 0..{full} for {n_coeffs} coefficients, got {sh_degree}")
    return degree


def rasterize(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    sh_coeffs: SHCoeffs | None,
    camera: Camera,
    *,
    sh_degree: int | None = None,
    colors: Tensor | None = None,
    background: Tensor | None = None,
    settings: RasterSettings | None = None,
) -> tuple[Tensor, Tensor, Tensor, dict[str, Any]]:
    """Renders Gaussians with the 3DGS image model.

    means: [N, 3]; quats: [N, 4] wxyz (unnormalised; zero = identity); scales: [N, 3] activated;
    opacities: [N] in [0, 1]; sh_coeffs: [N, K, 3] (K = 1, 4, 9, 16), or the pair (sh0 [N, 1, 3],
    shN [N, K - 1, 3]) as the model keeps them (the compiled kernels read them where they are), or
    None with colors [N, 3];
    camera: its viewmat [4, 4] world-to-camera (OpenCV), K [3, 3], width, height and depth range
    (near, far); background: [3] (None = black).

    Returns image [H, W, 3], alpha [H, W, 1], expected depth [H, W, 1] (sum w z / alpha; 0 where
    nothing is drawn) and info (see the package docstring).
    """
    return _render(means, quats, scales, opacities, sh_coeffs, camera, sh_degree, colors, background,
                   None, None, settings)


def rasterize_branched(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    sh_coeffs: SHCoeffs | None,
    camera: Camera,
    *,
    means_cov: Tensor,
    means_sh: Tensor,
    sh_degree: int | None = None,
    colors: Tensor | None = None,
    background: Tensor | None = None,
    settings: RasterSettings | None = None,
) -> tuple[Tensor, Tensor, Tensor, dict[str, Any]]:
    """:func:`rasterize` with each of the means' three paths through its own tensor, the renderer
    variant of the Blur-Trap branch analysis (``exploregs_plugin/analysis/branches.py``) and the
    branch ablation: ``means`` feeds the projected 2D mean and depth (the expected depth follows
    it), ``means_cov`` [N, 3] the covariance through the perspective Jacobian, ``means_sh`` [N, 3]
    the SH view direction. The same tensor three times renders exactly what :func:`rasterize` does.
    Torch and cpp backends only (gsplat has one means input): ``--model.raster.backend auto`` renders
    it with the torch reference where it would pick gsplat, and an explicit gsplat is refused."""
    return _render(means, quats, scales, opacities, sh_coeffs, camera, sh_degree, colors, background,
                   means_cov, means_sh, settings)


def _render(means, quats, scales, opacities, sh_coeffs, camera, sh_degree, colors, background,
            means_cov, means_sh, settings):  # fmt: skip
    """Checks the inputs, resolves the backend and renders (the body of both public variants)."""
    settings = settings or RasterSettings()
    if not isinstance(camera, Camera):
        raise TypeError(f"rasterize: argument 'camera' must be an exploregs_plugin.cameras.Camera, got "
                        f"{type(camera).__name__}")
    viewmat, K, width, height = camera.viewmat, camera.K, camera.width, camera.height
    near_plane, far_plane = float(camera.near), float(camera.far)
    degree = _validate(
        means, quats, scales, opacities, sh_coeffs, colors, viewmat, K, width, height,
        sh_degree, means_cov, means_sh, background,
    )  # fmt: skip
    backend = resolve_backend(settings, means.device)
    branched = (means_cov is not None and means_cov is not means) or (means_sh is not None and means_sh is not means)
    if backend == "gsplat" and branched:
        if settings.backend == "gsplat":
            raise BackendError("separate tensors for the covariance and SH paths of the means (rasterize_branched: "
                               "the branch analysis and exploregs-branch-ablation --model.detach-paths) need "
                               "--model.raster.backend torch or cpp")
        backend = "torch"  # auto on a GPU: gsplat has one means input, so the branches render with the reference
    if backend == "gsplat":
        return rasterize_gsplat(means, quats, scales, opacities, _joined(sh_coeffs), colors, degree, viewmat, K, int(width),
                                int(height), background, near_plane, far_plane, settings)
    problem = backend_problem(settings, means.device) if settings.backend == "cpp" else None
    if problem is not None:
        raise BackendError(problem)
    threads = thread_budget()  # the caller's thread count, before the projection goes single-threaded
    with single_threaded_ops():
        return _rasterize(
            means, quats, scales, opacities, sh_coeffs, viewmat, K, int(width), int(height), degree, colors,
            background, near_plane, far_plane, means_cov, means_sh, settings, backend == "cpp", threads,
        )  # fmt: skip


def _rasterize(
    means, quats, scales, opacities, sh_coeffs, viewmat, K, width, height, degree, colors, background,
    near_plane, far_plane, means_cov, means_sh, settings, compiled, threads,
):  # fmt: skip
    """Project every Gaussian, colour the visible ones, composite them and finish the images."""
    # the dtype and device of the means (no operator where they have them already)
    viewmat, K = (t if (t.dtype, t.device) == (means.dtype, means.device) else t.to(means) for t in (viewmat, K))
    if compiled and (means_cov is None or means_cov is means) and not (viewmat.requires_grad or K.requires_grad):
        proj = project_cpp(means, quats, scales, opacities, viewmat, K, width, height, near_plane, far_plane,
                           settings, threads)
    else:
        proj = project_gaussians(
            means, quats, scales, opacities, viewmat, K, width, height, near_plane, far_plane, settings, means_cov
        )
    camera_center = -(viewmat[:3, :3].T @ viewmat[:3, 3])
    if compiled:  # the compiled kernels read the visible rows of the full-size tensors
        img, visibility, n_pairs = _composite_compiled(
            proj, means, means_sh, sh_coeffs, colors, degree, camera_center, width, height, settings, threads)
    else:
        vis = torch.nonzero(proj.visible).squeeze(1)
        rgb = _colours(means, means_sh, _joined(sh_coeffs), colors, degree, vis, camera_center)
        img, visibility, n_pairs = _composite_visible(proj, vis, rgb, width, height, settings)
        if settings.visibility_stats:
            visibility = torch.zeros(means.shape[0], len(VISIBILITY_COLUMNS), dtype=means.dtype,
                                     device=means.device).index_copy_(
                0, vis, visibility)
    image, acc, depth = _finish(img, background, means, settings)
    info: dict[str, Any] = {
        "means2d": proj.means2d,
        "radii": proj.radii,
        "visible": proj.visible,
        "depths": proj.depths,
        "conics": proj.conics,
        "camera_center": camera_center,
        "width": width,
        "height": height,
        "n_cameras": 1,
        "n_pairs": n_pairs,
    }
    if settings.visibility_stats:
        info["visibility"] = visibility
    return image, acc, depth, info


def _colours(means, means_sh, sh_coeffs, colors, degree, vis, camera_center) -> Tensor:
    """[M, 3] colours of the visible rows ``vis``: the given ``colors``, or the SH evaluated in the
    direction from the camera centre (through ``means_sh`` when the SH path has its own tensor)."""
    if degree < 0:
        return colors.index_select(0, vis)
    src = means if means_sh is None else means_sh
    return sh_colors(sh_coeffs.index_select(0, vis), src.index_select(0, vis), camera_center, degree)


def _composite_visible(proj, vis, rgb, width, height, settings) -> tuple[Tensor, Tensor, int]:
    """Bin and alpha-composite the visible rows with the torch reference: ([H, W, 5] colour, depth
    and alpha, their visibility statistics [M, 3], the number of tile-Gaussian pairs)."""
    feats = torch.cat([rgb, proj.depths.index_select(0, vis)[:, None]], -1)  # [M, 4]
    means2d_vis = proj.means2d.index_select(0, vis)
    support = proj.support.index_select(0, vis)
    depths_vis = proj.depths.detach().index_select(0, vis)
    conics_vis, opac_vis = proj.conics.index_select(0, vis), proj.opacities.index_select(0, vis)
    bins = bin_gaussians(means2d_vis.detach(), support, depths_vis, width, height, settings.tile_size)
    out, visibility = composite(means2d_vis, conics_vis, opac_vis, feats, support, bins, settings,
                                absgrad_into=(proj.means2d, vis))
    ts = settings.tile_size
    img = out.view(bins.tiles_y, bins.tiles_x, ts, ts, -1).permute(0, 2, 1, 3, 4)
    return img.reshape(bins.tiles_y * ts, bins.tiles_x * ts, -1)[:height, :width], visibility, bins.n_pairs


def _composite_compiled(proj, means, means_sh, sh_coeffs, colors, degree, camera_center, width, height, settings,
                        threads) -> tuple[Tensor, Tensor, int]:
    """Colour, bin and composite with the compiled kernels, which read the visible rows of the
    full-size tensors: no gather of the visible rows and no scatter of their gradients back (about
    a dozen operators a view, forward and backward). Returns ([H, W, 5] colour, depth and alpha,
    the visibility statistics [N, 3] (0 for a row not drawn), the number of tile-Gaussian pairs)."""
    src = means if means_sh is None else means_sh
    if degree < 0:
        rgb = colors
    elif src is means and not camera_center.requires_grad:
        rgb = sh_colors_cpp(sh_coeffs, means, proj.visible, camera_center, degree, threads)
    else:  # the branch ablation's SH path, or a camera with a gradient: torch's SH of every row
        rgb = sh_colors(_joined(sh_coeffs), src, camera_center, degree)
    feats = torch.cat([rgb, proj.depths[:, None]], -1)  # [N, 4]
    bins = CppBins(proj.means2d, proj.support, proj.depths, width, height, settings.tile_size, proj.visible,
                   proj.conics, proj.opacities, settings.alpha_min)
    img, visibility = composite_cpp(proj.means2d, proj.conics, proj.opacities, feats, proj.support, bins, settings,
                                    threads)
    return img, visibility, bins.n_pairs


def _finish(img: Tensor, background: Tensor | None, means: Tensor, settings: RasterSettings
            ) -> tuple[Tensor, Tensor, Tensor]:
    """Image on the background, accumulated alpha, expected depth D / A (0 where nothing is drawn)."""
    acc = img[..., 4:5]
    image = img[..., :3]
    if background is not None:
        image = image + (1.0 - acc) * background.to(means)
    depth = img[..., 3:4] / acc.clamp_min(ALPHA_DEPTH_MIN)
    cpu = means.device.type == "cpu"
    # inside a CPU run's training step every op is single-threaded already (Pipeline.train_step
    # holds single_threaded_ops through the backward): no identity node and its three copies
    if cpu and settings.single_threaded_backward and torch.is_grad_enabled() and image.requires_grad \
            and not single_threaded_now():
        image, acc, depth = _SingleThreadedBackward.apply(image, acc, depth)
    return image, acc, depth
