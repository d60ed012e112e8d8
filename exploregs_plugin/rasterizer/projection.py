"""EWA projection of 3D Gaussians to the screen (O(N), plain autograd).

Three tensors may carry the 3D mean, one per path through which it reaches the image:
``means`` -> projected 2D mean (and depth), ``means_cov`` -> 2D covariance through the
perspective Jacobian. (The third, the SH view direction, lives in ``sh.py``.)
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import torch
from torch import Tensor

from .settings import RasterSettings

# A quaternion whose squared norm is at or below this is treated as the identity rotation
# (|q| <= 1e-12), so the normalisation never divides by zero and its gradient stays finite.
QUAT_NORM2_MIN = 1e-24
# Floor of the 2D covariance determinant before inversion (it is >= eps2d^2 in exact maths).
DET_MIN = 1e-20
# Margins of the opacity-aware support (relative, then pixels), far above float rounding of the
# alpha a pixel gets, so that the narrower box never drops a pair with alpha >= alpha_min.
SUPPORT_MARGIN_REL = 1e-3
SUPPORT_MARGIN_PX = 1e-2


def quats_to_rotmats(quats: Tensor, few_operators: bool = False) -> Tensor:
    """Rotation matrices from wxyz quaternions (normalised here; zero quaternion = identity).

    quats: [N, 4]; returns [N, 3, 3]. Every entry is 1 - 2 (a + b) on the diagonal and 2 (a +- b)
    off it, a and b products of two components. ``few_operators``: the same floats from one
    outer product of q and two gathers of it (about a dozen operators instead of forty), for a
    caller with few rows and no gradient (the split's children at every step of Seed+Split). On
    one CPU thread it took 0.04 against 0.08 ms at 64 rows and 2.2 against 1.0 ms at 20,000 (the
    fastest of 3 x 200 calls; the same bits, signed zeros included: tests/test_rasterizer_reference.py).
    """
    n2 = (quats * quats).sum(-1, keepdim=True)
    identity = torch.zeros_like(quats)
    identity[:, 0] = 1.0
    q = torch.where(n2 > QUAT_NORM2_MIN, quats, identity)
    q = q * torch.rsqrt((q * q).sum(-1, keepdim=True))
    if few_operators:
        first, second, sign, diagonal = _rotation_terms(q.device, q.dtype)
        products = (q[:, :, None] * q[:, None, :]).reshape(-1, 16)  # q_i q_j: the products below, exactly
        # b * -1 is -b exactly and a + (-b) is a - b, so each entry is the same float as below
        twice = 2 * (products.index_select(1, first) + products.index_select(1, second) * sign)
        return torch.where(diagonal, 1 - twice, twice).reshape(-1, 3, 3)
    w, x, y, z = q.unbind(-1)
    rows = [
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ]  # fmt: skip
    return torch.stack(rows, dim=-1).reshape(-1, 3, 3)


@functools.lru_cache(maxsize=8)
def _rotation_terms(device: torch.device, dtype: torch.dtype) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """For each entry of R (row-major): the index in q q^T (i * 4 + j, q = w, x, y, z) of its
    products a and b, the sign of b, and whether it is on the diagonal. Made once per device."""
    w, x, y, z = range(4)
    pairs = [((y, y), (z, z), 1), ((x, y), (w, z), -1), ((x, z), (w, y), 1),
             ((x, y), (w, z), 1), ((x, x), (z, z), 1), ((y, z), (w, x), -1),
             ((x, z), (w, y), -1), ((y, z), (w, x), 1), ((x, x), (y, y), 1)]  # fmt: skip
    first = torch.tensor([a[0] * 4 + a[1] for a, _, _ in pairs], device=device)
    second = torch.tensor([b[0] * 4 + b[1] for _, b, _ in pairs], device=device)
    sign = torch.tensor([s for _, _, s in pairs], dtype=dtype, device=device)
    diagonal = torch.tensor([i in (0, 4, 8) for i in range(9)], device=device)
    return first, second, sign, diagonal


def covariances_3d(quats: Tensor, scales: Tensor) -> Tensor:
    """World covariance R diag(s^2) R^T. quats: [N, 4]; scales: [N, 3] (activated); returns [N, 3, 3]."""
    m = quats_to_rotmats(quats) * scales[:, None, :]
    return m @ m.transpose(1, 2)


@dataclass
class Projected:
    """Per-Gaussian screen quantities for one camera (all [N, ...], defined for culled ones too)."""

    means2d: Tensor
    """[N, 2] pixel coordinates of the projected mean (from the ``means`` path)."""
    conics: Tensor
    """[N, 3] (a, b, c) of the inverse 2D covariance: power = -0.5 (a dx^2 + 2 b dx dy + c dy^2)."""
    opacities: Tensor
    """[N] opacity after the optional anti-aliasing compensation."""
    depths: Tensor
    """[N] camera-space z of the mean (from the ``means`` path)."""
    radii: Tensor
    """[N, 2] int32 support half-widths in pixels; 0 where culled."""
    support: Tensor
    """[N, 2] float half-widths of the box in which pixels composite: ``radii``'s box narrowed to
    where alpha can reach alpha_min (:func:`opacity_support`); the pairs it leaves out have
    alpha < alpha_min, so the image is that of ``radii``'s box."""
    visible: Tensor
    """[N] bool: in front of the near plane, before the far plane, support box meets the image."""


def _intrinsics(K: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    return K[0, 0], K[1, 1], K[0, 2], K[1, 2]


def project_gaussians(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    viewmat: Tensor,
    K: Tensor,
    width: int,
    height: int,
    near_plane: float,
    far_plane: float,
    settings: RasterSettings,
    means_cov: Tensor | None = None,
) -> Projected:
    """EWA splatting: 2D means, conics, radii and visibility.

    means, means_cov: [N, 3]; quats: [N, 4]; scales: [N, 3]; opacities: [N];
    viewmat: [4, 4] world-to-camera; K: [3, 3].
    """
    if means_cov is None:
        means_cov = means
    rot, trans = viewmat[:3, :3], viewmat[:3, 3]
    fx, fy, cx, cy = _intrinsics(K)

    p_cam = means @ rot.T + trans  # [N, 3]
    depth = p_cam[:, 2]
    with torch.no_grad():
        depth_ok = (depth > near_plane) & (depth < far_plane)
    # Culled rows get z = 1 so that no division below produces inf/NaN (their values are unused,
    # and NaN would otherwise leak into gradients through torch.where).
    one = torch.ones_like(depth)
    z = torch.where(depth_ok, depth, one)
    means2d = torch.stack([fx * p_cam[:, 0] / z + cx, fy * p_cam[:, 1] / z + cy], dim=-1)

    # Covariance path: perspective Jacobian at the (guard-band clamped) position.
    pc = p_cam if means_cov is means else means_cov @ rot.T + trans
    zc = torch.where(depth_ok, pc[:, 2], one)
    tan_x, tan_y = 0.5 * width / fx, 0.5 * height / fy
    lim_x_neg, lim_x_pos = cx / fx + settings.guard_band * tan_x, (width - cx) / fx + settings.guard_band * tan_x
    lim_y_neg, lim_y_pos = cy / fy + settings.guard_band * tan_y, (height - cy) / fy + settings.guard_band * tan_y
    xz = torch.clamp(pc[:, 0] / zc, min=-lim_x_neg, max=lim_x_pos)
    yz = torch.clamp(pc[:, 1] / zc, min=-lim_y_neg, max=lim_y_pos)
    zero = torch.zeros_like(zc)
    jac = torch.stack(
        [fx / zc, zero, -fx * xz / zc, zero, fy / zc, -fy * yz / zc], dim=-1
    ).reshape(-1, 2, 3)  # d(u, v)/d(x, y, z) with x = z * clamp(x/z)
    jw = jac @ rot  # [N, 2, 3]
    m = jw @ quats_to_rotmats(quats) * scales[:, None, :]  # J W R S
    cov2d = m @ m.transpose(1, 2)  # [N, 2, 2]

    a = cov2d[:, 0, 0] + settings.eps2d
    c = cov2d[:, 1, 1] + settings.eps2d
    b = cov2d[:, 0, 1]
    det_raw = a * c - b * b
    det = det_raw.clamp_min(DET_MIN)
    conics = torch.stack([c / det, -b / det, a / det], dim=-1)
    if settings.antialiased:
        det_orig = cov2d[:, 0, 0] * cov2d[:, 1, 1] - b * b
        opacities = opacities * torch.sqrt((det_orig / det).clamp_min(0.0))

    with torch.no_grad():
        r = torch.ceil(settings.sigma_radius * torch.sqrt(torch.stack([a, c], dim=-1).clamp_min(0.0)))
        finite = torch.isfinite(means2d).all(-1) & torch.isfinite(conics).all(-1) & torch.isfinite(r).all(-1)
        # The support box holds pixel centres i + 0.5 with |i + 0.5 - mean| <= radius.
        lo = torch.ceil(means2d - r - 0.5)
        hi = torch.floor(means2d + r - 0.5)
        size = torch.tensor([width, height], dtype=lo.dtype, device=lo.device)
        on_screen = ((hi >= 0) & (lo <= size - 1)).all(-1)
        visible = depth_ok & finite & on_screen & (opacities > 0)
        radii = torch.where(visible[:, None], r.clamp_max(2**30), torch.zeros_like(r)).to(torch.int32)
        support = opacity_support(r, torch.stack([a, c], dim=-1), opacities, det_raw > DET_MIN, settings.alpha_min)
    return Projected(means2d, conics, opacities, depth, radii, support, visible)


def opacity_support(box: Tensor, variances: Tensor, opacities: Tensor, exact: Tensor, alpha_min: float) -> Tensor:
    """The support box ``box`` [N, 2] narrowed to where a pixel's alpha can reach ``alpha_min``.

    alpha = o exp(-q / 2) >= alpha_min only inside the ellipse q <= t = 2 ln(o / alpha_min), whose
    bounding box is |dx| <= sqrt(t a), |dy| <= sqrt(t c), with (a, c) = ``variances`` [N, 2], the
    diagonal of the 2D covariance that the conic inverts. It is narrower than the sigma_radius box
    where t < sigma_radius^2 (at 3 sigma: o < exp(4.5) alpha_min ~ 0.35; o = 0.01 after an opacity
    reset gives 1.37 sigma). Pairs outside it are skipped by the alpha test anyway: the image and
    gradients do not change, there are only fewer pairs to composite. Rows whose determinant was
    floored (``exact`` False: the conic then inverts a wider covariance) keep ``box``."""
    t = 2.0 * torch.log(opacities.detach().clamp_min(alpha_min) / alpha_min)  # >= 0
    tight = torch.ceil(torch.sqrt(t[:, None] * variances.detach().clamp_min(0.0)) * (1.0 + SUPPORT_MARGIN_REL)
                       + SUPPORT_MARGIN_PX)
    return torch.where(exact[:, None], torch.fmin(box, tight), box)  # fmin: a NaN row keeps its box
