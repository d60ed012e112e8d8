"""Dense reference renderer for tests and error measurements.

Written independently of the fast path (no shared helpers): every pixel is tested against
every Gaussian, compositing walks the depth-sorted Gaussians one by one, and autograd provides
all gradients. Memory is O(pixels x Gaussians): use it on small images, in float64.
The support rule is the fast path's: the pixel centre lies in the per-axis box
|dx| <= ceil(sigma_radius * sigma_x), |dy| <= ceil(sigma_radius * sigma_y), power <= 0 and
alpha >= alpha_min.
"""

from __future__ import annotations

import torch
from torch import Tensor

from ..cameras import Camera
from .settings import RasterSettings

_SH = {
    0: [lambda x, y, z: 0.28209479177387814 + 0 * x],
    1: [
        lambda x, y, z: -0.4886025119029199 * y,
        lambda x, y, z: 0.4886025119029199 * z,
        lambda x, y, z: -0.4886025119029199 * x,
    ],
    2: [
        lambda x, y, z: 1.0925484305920792 * x * y,
        lambda x, y, z: -1.0925484305920792 * y * z,
        lambda x, y, z: 0.31539156525252005 * (2 * z * z - x * x - y * y),
        lambda x, y, z: -1.0925484305920792 * x * z,
        lambda x, y, z: 0.5462742152960396 * (x * x - y * y),
    ],
    3: [
        lambda x, y, z: -0.5900435899266435 * y * (3 * x * x - y * y),
        lambda x, y, z: 2.890611442640554 * x * y * z,
        lambda x, y, z: -0.4570457994644658 * y * (4 * z * z - x * x - y * y),
        lambda x, y, z: 0.3731763325901154 * z * (2 * z * z - 3 * x * x - 3 * y * y),
        lambda x, y, z: -0.4570457994644658 * x * (4 * z * z - x * x - y * y),
        lambda x, y, z: 1.445305721320277 * z * (x * x - y * y),
        lambda x, y, z: -0.5900435899266435 * x * (x * x - 3 * y * y),
    ],
}


def _rotation(q: Tensor) -> Tensor:
    """wxyz -> [N, 3, 3]; |q|^2 <= 1e-24 means identity."""
    small = (q * q).sum(-1) <= 1e-24
    q = torch.where(small[:, None], torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=q.dtype), q)
    q = q / torch.linalg.vector_norm(q, dim=-1, keepdim=True)
    w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    r0 = torch.stack([w * w + x * x - y * y - z * z, 2 * (x * y - w * z), 2 * (x * z + w * y)], -1)
    r1 = torch.stack([2 * (x * y + w * z), w * w - x * x + y * y - z * z, 2 * (y * z - w * x)], -1)
    r2 = torch.stack([2 * (x * z - w * y), 2 * (y * z + w * x), w * w - x * x - y * y + z * z], -1)
    return torch.stack([r0, r1, r2], -2)


def reference_rasterize(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    sh_coeffs: Tensor | None,
    camera: Camera,
    *,
    sh_degree: int | None = None,
    colors: Tensor | None = None,
    background: Tensor | None = None,
    means_cov: Tensor | None = None,
    means_sh: Tensor | None = None,
    settings: RasterSettings | None = None,
    window: tuple[int, int, int, int] | None = None,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Same arguments as ``rasterize``; returns image [h, w, 3], alpha [h, w, 1],
    expected depth [h, w, 1] and means2d [N, 2] (in the dtype of ``means``).

    ``window = (x0, y0, w, h)`` evaluates only those pixels of the width x height image (the
    camera model is unchanged); None = the whole image.
    """
    s = settings or RasterSettings()
    viewmat, K, width, height = camera.viewmat, camera.K, camera.width, camera.height
    near_plane, far_plane = float(camera.near), float(camera.far)
    dt = means.dtype
    mc = means if means_cov is None else means_cov
    ms = means if means_sh is None else means_sh
    V, Kt = viewmat.to(dt), K.to(dt)
    Rv, tv = V[:3, :3], V[:3, 3]
    fx, fy, cx, cy = Kt[0, 0], Kt[1, 1], Kt[0, 2], Kt[1, 2]
    n = means.shape[0]

    cam = torch.einsum("ij,nj->ni", Rv, means) + tv
    depth = cam[:, 2]
    alive = (depth > near_plane) & (depth < far_plane)
    zs = torch.where(alive, depth, torch.ones_like(depth))
    u = fx * cam[:, 0] / zs + cx
    v = fy * cam[:, 1] / zs + cy

    camc = torch.einsum("ij,nj->ni", Rv, mc) + tv
    zc = torch.where(alive, camc[:, 2], torch.ones_like(depth))
    gx = s.guard_band * width / (2 * fx)
    gy = s.guard_band * height / (2 * fy)
    tx = zc * torch.clamp(camc[:, 0] / zc, -(cx / fx + gx), (width - cx) / fx + gx)
    ty = zc * torch.clamp(camc[:, 1] / zc, -(cy / fy + gy), (height - cy) / fy + gy)
    J = torch.zeros(n, 2, 3, dtype=dt)
    J[:, 0, 0] = fx / zc
    J[:, 0, 2] = -fx * tx / (zc * zc)
    J[:, 1, 1] = fy / zc
    J[:, 1, 2] = -fy * ty / (zc * zc)
    Rg = _rotation(quats)
    sigma3 = Rg @ torch.diag_embed(scales * scales) @ Rg.transpose(1, 2)
    T = J @ Rv
    cov = T @ sigma3 @ T.transpose(1, 2)
    cxx = cov[:, 0, 0] + s.eps2d
    cyy = cov[:, 1, 1] + s.eps2d
    cxy = cov[:, 0, 1]
    det = torch.clamp(cxx * cyy - cxy * cxy, min=1e-20)
    op = opacities
    if s.antialiased:
        raw = cov[:, 0, 0] * cov[:, 1, 1] - cxy * cxy
        op = op * torch.sqrt(torch.clamp(raw / det, min=0.0))
    with torch.no_grad():
        rx = torch.ceil(s.sigma_radius * torch.sqrt(cxx))
        ry = torch.ceil(s.sigma_radius * torch.sqrt(cyy))

    means2d = torch.stack([u, v], -1)
    if colors is not None:
        col = colors.to(dt)
    else:
        kk = sh_coeffs.shape[1]
        deg = int(round(kk**0.5)) - 1 if sh_degree is None else sh_degree
        d = ms - (-(Rv.T @ tv))
        d = d / torch.clamp(torch.linalg.vector_norm(d, dim=-1, keepdim=True), min=1e-15)
        basis = [f(d[:, 0], d[:, 1], d[:, 2]) for lvl in range(deg + 1) for f in _SH[lvl]]
        col = torch.clamp(torch.einsum("nb,nbc->nc", torch.stack(basis, -1), sh_coeffs[:, : len(basis)]) + 0.5, min=0)

    x0, y0, ww, hh = (0, 0, width, height) if window is None else window
    jj, ii = torch.meshgrid(torch.arange(y0, y0 + hh, dtype=dt), torch.arange(x0, x0 + ww, dtype=dt), indexing="ij")
    # Gaussians whose support box misses the window contribute nothing: drop them early.
    with torch.no_grad():
        near_win = alive & (u + rx >= x0 + 0.5) & (u - rx <= x0 + ww - 0.5) & (v + ry >= y0 + 0.5)
        near_win = near_win & (v - ry <= y0 + hh - 0.5)
    keep = torch.nonzero(near_win).squeeze(1)
    u, v, rx, ry, op, col, depth, alive = (t[keep] for t in (u, v, rx, ry, op, col, depth, alive))
    cxx, cyy, cxy, det = (t[keep] for t in (cxx, cyy, cxy, det))
    px = (ii.reshape(-1) + 0.5)[:, None]
    py = (jj.reshape(-1) + 0.5)[:, None]
    ddx = px - u[None, :]
    ddy = py - v[None, :]
    power = -0.5 * (cyy / det * ddx * ddx + cxx / det * ddy * ddy) + cxy / det * ddx * ddy
    a = torch.minimum(op[None, :] * torch.exp(power), torch.tensor(s.alpha_max, dtype=dt))
    use = alive[None, :] & (ddx.abs() <= rx[None, :]) & (ddy.abs() <= ry[None, :])
    use = use & (power <= 0) & (a >= s.alpha_min)
    a = torch.where(use, a, torch.zeros_like(a))

    P = px.shape[0]
    trans = torch.ones(P, dtype=dt)
    done = torch.zeros(P, dtype=torch.bool)
    rgb = torch.zeros(P, 3, dtype=dt)
    dep = torch.zeros(P, dtype=dt)
    for g in torch.argsort(depth.detach(), stable=True).tolist():
        ag = a[:, g]
        nxt = trans * (1 - ag)
        done = done | (nxt < s.transmittance_min)
        wg = torch.where(done, torch.zeros_like(ag), ag * trans)
        rgb = rgb + wg[:, None] * col[g]
        dep = dep + wg * depth[g]
        trans = torch.where(done, trans, nxt)
    acc = 1 - trans
    if background is not None:
        rgb = rgb + trans[:, None] * background.to(dt)
    ed = dep / torch.clamp(acc, min=1e-10)
    return (
        rgb.reshape(hh, ww, 3),
        acc.reshape(hh, ww, 1),
        ed.reshape(hh, ww, 1),
        means2d,
    )
