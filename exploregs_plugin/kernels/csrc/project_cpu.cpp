// EWA projection of 3D Gaussians to the screen on the CPU, forward and backward: the image model
// of exploregs_plugin/rasterizer/projection.py, one Gaussian per loop iteration.
//
// Forward, per Gaussian (W, t: world-to-camera rotation and translation):
//   p = W m + t, depth = p_z, culled unless near < p_z < far (then z = 1 keeps every division finite),
//   mean2d = (fx p_x / z + cx, fy p_y / z + cy),
//   J = [[fx / z, 0, -fx xz / z], [0, fy / z, -fy yz / z]], xz = clamp(p_x / z) to the guard band,
//   M = J W R(q) diag(s), cov2d = M M^T, (a, b, c) = (cov_00 + eps2d, cov_01, cov_11 + eps2d),
//   det = max(a c - b^2, 1e-20), conic = (c, -b, a) / det, radius = ceil(sigma_radius sqrt((a, c))),
//   antialiased: o' = o sqrt(max((cov_00 cov_11 - b^2) / det, 0)),
//   support = min(radius, ceil(sqrt(t (a, c)) (1 + 1e-3) + 1e-2)), t = 2 ln(max(o', alpha_min) / alpha_min)
//   where the determinant is not floored (projection.py's opacity_support: alpha = o' exp(-q / 2)
//   reaches alpha_min only inside q <= t, and that ellipse's bounding box is sqrt(t (a, c))).
// Backward: the chain rule through exactly these expressions; zero through the guard-band clamp
// and the determinant floor where they are active, as autograd gives for the torch code.
// Every Gaussian writes only its own rows, so the result does not depend on the thread count.

// ATen's tensor headers only (outputs made through tensors.h): the whole of torch/extension.h
// costs about five times the CPU time to compile (docs/training.md, "Building the kernels").
#include "tensors.h"
#include <ATen/Dispatch.h>
#include <ATen/core/Tensor.h>

#include <omp.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

namespace {

constexpr double QUAT_NORM2_MIN = 1e-24;  // |q| <= 1e-12: the identity rotation
constexpr double DET_MIN = 1e-20;         // floor of the 2D covariance determinant
constexpr double SUPPORT_MARGIN_REL = 1e-3;  // margins of the opacity-aware support (projection.py)
constexpr double SUPPORT_MARGIN_PX = 1e-2;

template <typename scalar_t>
struct Camera {
  scalar_t W[9], t[3], fx, fy, cx, cy;
  scalar_t lim_x_neg, lim_x_pos, lim_y_neg, lim_y_pos;
  scalar_t near, far, eps2d, sigma_radius;
  int64_t width, height;
  bool antialiased;
};

// Rotation matrix (row-major) of the normalised quaternion q = (w, x, y, z).
template <typename scalar_t>
inline void rotmat(const scalar_t* q, scalar_t* R) {
  const scalar_t w = q[0], x = q[1], y = q[2], z = q[3];
  R[0] = 1 - 2 * (y * y + z * z);
  R[1] = 2 * (x * y - w * z);
  R[2] = 2 * (x * z + w * y);
  R[3] = 2 * (x * y + w * z);
  R[4] = 1 - 2 * (x * x + z * z);
  R[5] = 2 * (y * z - w * x);
  R[6] = 2 * (x * z - w * y);
  R[7] = 2 * (y * z + w * x);
  R[8] = 1 - 2 * (x * x + y * y);
}

// Normalised quaternion and 1 / |q| (0 for a quaternion treated as the identity).
template <typename scalar_t>
inline scalar_t normalise(const scalar_t* q, scalar_t* qn) {
  const scalar_t n2 = q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3];
  if (!(n2 > scalar_t(QUAT_NORM2_MIN))) {
    qn[0] = 1;
    qn[1] = qn[2] = qn[3] = 0;
    return 0;
  }
  const scalar_t inv = scalar_t(1) / std::sqrt(n2);
  for (int k = 0; k < 4; ++k) qn[k] = q[k] * inv;
  return inv;
}

// Everything the forward computes for one Gaussian that the backward needs again.
template <typename scalar_t>
struct Geometry {
  scalar_t p[3], z, xz, yz;
  bool depth_ok, clamp_x, clamp_y;  // clamp_*: the guard band holds x/z (no gradient through it)
  scalar_t qn[4], qinv, R[9], JW[6], RS[9], M[6];
  scalar_t c00, c11, a, b, c, det;  // c00, c11: the 2D covariance before the low-pass
  bool det_floor;
};

template <typename scalar_t>
inline Geometry<scalar_t> geometry(const Camera<scalar_t>& cam, const scalar_t* m, const scalar_t* q,
                                   const scalar_t* s) {
  Geometry<scalar_t> g;
  for (int r = 0; r < 3; ++r) g.p[r] = cam.W[3 * r] * m[0] + cam.W[3 * r + 1] * m[1] + cam.W[3 * r + 2] * m[2] + cam.t[r];
  g.depth_ok = g.p[2] > cam.near && g.p[2] < cam.far;
  g.z = g.depth_ok ? g.p[2] : scalar_t(1);
  const scalar_t xr = g.p[0] / g.z, yr = g.p[1] / g.z;
  g.xz = std::min(std::max(xr, -cam.lim_x_neg), cam.lim_x_pos);
  g.yz = std::min(std::max(yr, -cam.lim_y_neg), cam.lim_y_pos);
  g.clamp_x = !(xr >= -cam.lim_x_neg && xr <= cam.lim_x_pos);
  g.clamp_y = !(yr >= -cam.lim_y_neg && yr <= cam.lim_y_pos);
  const scalar_t J[6] = {cam.fx / g.z, 0, -cam.fx * g.xz / g.z, 0, cam.fy / g.z, -cam.fy * g.yz / g.z};
  for (int r = 0; r < 2; ++r)
    for (int k = 0; k < 3; ++k)
      g.JW[3 * r + k] = J[3 * r] * cam.W[k] + J[3 * r + 1] * cam.W[3 + k] + J[3 * r + 2] * cam.W[6 + k];
  g.qinv = normalise(q, g.qn);
  rotmat(g.qn, g.R);
  for (int r = 0; r < 3; ++r)
    for (int k = 0; k < 3; ++k) g.RS[3 * r + k] = g.R[3 * r + k] * s[k];
  for (int r = 0; r < 2; ++r)
    for (int k = 0; k < 3; ++k)
      g.M[3 * r + k] = g.JW[3 * r] * g.RS[k] + g.JW[3 * r + 1] * g.RS[3 + k] + g.JW[3 * r + 2] * g.RS[6 + k];
  const scalar_t c00 = g.M[0] * g.M[0] + g.M[1] * g.M[1] + g.M[2] * g.M[2];
  const scalar_t c01 = g.M[0] * g.M[3] + g.M[1] * g.M[4] + g.M[2] * g.M[5];
  const scalar_t c11 = g.M[3] * g.M[3] + g.M[4] * g.M[4] + g.M[5] * g.M[5];
  g.c00 = c00;
  g.c11 = c11;
  g.a = c00 + cam.eps2d;
  g.c = c11 + cam.eps2d;
  g.b = c01;
  const scalar_t det = g.a * g.c - g.b * g.b;
  g.det_floor = !(det > scalar_t(DET_MIN));
  g.det = g.det_floor ? scalar_t(DET_MIN) : det;
  return g;
}

template <typename scalar_t>
void project_forward_impl(const Camera<scalar_t>& cam, int64_t n, const scalar_t* means, const scalar_t* quats,
                          const scalar_t* scales, const scalar_t* opac, scalar_t* means2d, scalar_t* conics,
                          scalar_t* opac_out, scalar_t* depths, int32_t* radii, scalar_t* support, bool* visible,
                          scalar_t alpha_min, int64_t threads) {
#pragma omp parallel for num_threads(std::max<int64_t>(1, threads)) schedule(static)
  for (int64_t i = 0; i < n; ++i) {
    const Geometry<scalar_t> g = geometry(cam, means + 3 * i, quats + 4 * i, scales + 3 * i);
    const scalar_t u = cam.fx * g.p[0] / g.z + cam.cx, v = cam.fy * g.p[1] / g.z + cam.cy;
    means2d[2 * i] = u;
    means2d[2 * i + 1] = v;
    depths[i] = g.p[2];
    const scalar_t k0 = g.c / g.det, k1 = -g.b / g.det, k2 = g.a / g.det;
    conics[3 * i] = k0;
    conics[3 * i + 1] = k1;
    conics[3 * i + 2] = k2;
    scalar_t o = opac[i];
    if (cam.antialiased) {
      const scalar_t det_orig = g.c00 * g.c11 - g.b * g.b;
      o = o * std::sqrt(std::max(det_orig / g.det, scalar_t(0)));
    }
    opac_out[i] = o;
    const scalar_t rx = std::ceil(cam.sigma_radius * std::sqrt(std::max(g.a, scalar_t(0))));
    const scalar_t ry = std::ceil(cam.sigma_radius * std::sqrt(std::max(g.c, scalar_t(0))));
    scalar_t sx = rx, sy = ry;
    if (!g.det_floor) {
      const scalar_t t = 2 * std::log(std::max(o, alpha_min) / alpha_min);
      const scalar_t a = std::max(g.a, scalar_t(0)), c = std::max(g.c, scalar_t(0));
      const scalar_t tx = std::ceil(std::sqrt(t * a) * scalar_t(1 + SUPPORT_MARGIN_REL) + scalar_t(SUPPORT_MARGIN_PX));
      const scalar_t ty = std::ceil(std::sqrt(t * c) * scalar_t(1 + SUPPORT_MARGIN_REL) + scalar_t(SUPPORT_MARGIN_PX));
      sx = std::fmin(rx, tx);  // fmin: a NaN keeps the sigma_radius box
      sy = std::fmin(ry, ty);
    }
    support[2 * i] = sx;
    support[2 * i + 1] = sy;
    const bool finite = std::isfinite(u) && std::isfinite(v) && std::isfinite(k0) && std::isfinite(k1) &&
                        std::isfinite(k2) && std::isfinite(rx) && std::isfinite(ry);
    // the support box holds pixel centres i + 0.5 with |i + 0.5 - mean| <= radius
    const bool on_screen = std::floor(u + rx - scalar_t(0.5)) >= 0 && std::ceil(u - rx - scalar_t(0.5)) <= cam.width - 1 &&
                           std::floor(v + ry - scalar_t(0.5)) >= 0 && std::ceil(v - ry - scalar_t(0.5)) <= cam.height - 1;
    const bool vis = g.depth_ok && finite && on_screen && o > 0;
    visible[i] = vis;
    const scalar_t cap = scalar_t(1 << 30);
    radii[2 * i] = vis ? static_cast<int32_t>(std::min(rx, cap)) : 0;
    radii[2 * i + 1] = vis ? static_cast<int32_t>(std::min(ry, cap)) : 0;
  }
}

// Row strides of the output gradients: the compositor's backward hands them over as columns of
// one [N, 6 + F] block (a copy of each into its own tensor was four operators a view).
struct RowStrides {
  int64_t means2d, conics, opac, depths;
};

template <typename scalar_t>
void project_backward_impl(const Camera<scalar_t>& cam, int64_t n, const scalar_t* means, const scalar_t* quats,
                           const scalar_t* scales, const scalar_t* opac, const scalar_t* g_means2d,
                           const scalar_t* g_conics, const scalar_t* g_opac, const scalar_t* g_depths,
                           const RowStrides& gs, scalar_t* d_means, scalar_t* d_quats, scalar_t* d_scales,
                           scalar_t* d_opac, int64_t threads) {
#pragma omp parallel for num_threads(std::max<int64_t>(1, threads)) schedule(static)
  for (int64_t i = 0; i < n; ++i) {
    const scalar_t* s = scales + 3 * i;
    const Geometry<scalar_t> g = geometry(cam, means + 3 * i, quats + 4 * i, s);
    scalar_t dp[3] = {0, 0, g_depths[i * gs.depths]};  // dL/dp (camera frame)
    scalar_t dz = 0;                          // dL/dz through the divisions (z = p_z when depth_ok)
    // mean2d = (fx p_x / z + cx, fy p_y / z + cy)
    const scalar_t gu = g_means2d[i * gs.means2d], gv = g_means2d[i * gs.means2d + 1];
    dp[0] += gu * cam.fx / g.z;
    dp[1] += gv * cam.fy / g.z;
    dz -= (gu * cam.fx * g.p[0] + gv * cam.fy * g.p[1]) / (g.z * g.z);
    // conic = (c, -b, a) / det
    const scalar_t *gc = g_conics + i * gs.conics, g0 = gc[0], g1 = gc[1], g2 = gc[2];
    const scalar_t inv_det = scalar_t(1) / g.det;
    scalar_t d_det = -(g0 * g.c - g1 * g.b + g2 * g.a) * inv_det * inv_det;
    scalar_t da = g2 * inv_det, db = -g1 * inv_det, dc = g0 * inv_det;
    // opacity (antialiased: o sqrt(det_orig / det))
    scalar_t go = g_opac[i * gs.opac];
    if (cam.antialiased) {
      const scalar_t det_orig = g.c00 * g.c11 - g.b * g.b;
      const scalar_t ratio = det_orig / g.det;
      if (ratio > 0) {
        const scalar_t root = std::sqrt(ratio);
        const scalar_t d_ratio = go * opac[i] * scalar_t(0.5) / root;
        da += d_ratio * g.c11 / g.det;
        dc += d_ratio * g.c00 / g.det;
        db += d_ratio * (-2 * g.b) / g.det;
        d_det -= d_ratio * det_orig / (g.det * g.det);
        go = go * root;
      } else {
        go = 0;
      }
    }
    d_opac[i] = go;
    if (!g.det_floor) {  // det = a c - b^2
      da += d_det * g.c;
      dc += d_det * g.a;
      db -= 2 * d_det * g.b;
    }
    // a = M0.M0 + eps, b = M0.M1, c = M1.M1 + eps
    scalar_t dM[6];
    for (int k = 0; k < 3; ++k) {
      dM[k] = 2 * da * g.M[k] + db * g.M[3 + k];
      dM[3 + k] = 2 * dc * g.M[3 + k] + db * g.M[k];
    }
    // M = JW RS
    scalar_t dJW[6], dRS[9];
    for (int r = 0; r < 2; ++r)
      for (int k = 0; k < 3; ++k)
        dJW[3 * r + k] = dM[3 * r] * g.RS[3 * k] + dM[3 * r + 1] * g.RS[3 * k + 1] + dM[3 * r + 2] * g.RS[3 * k + 2];
    for (int r = 0; r < 3; ++r)
      for (int k = 0; k < 3; ++k) dRS[3 * r + k] = g.JW[r] * dM[k] + g.JW[3 + r] * dM[3 + k];
    // RS = R diag(s)
    scalar_t dR[9];
    for (int k = 0; k < 3; ++k) {
      d_scales[3 * i + k] = dRS[k] * g.R[k] + dRS[3 + k] * g.R[3 + k] + dRS[6 + k] * g.R[6 + k];
      for (int r = 0; r < 3; ++r) dR[3 * r + k] = dRS[3 * r + k] * s[k];
    }
    // R(qn), then qn = q / |q|
    const scalar_t w = g.qn[0], x = g.qn[1], y = g.qn[2], zq = g.qn[3];
    scalar_t dqn[4];
    dqn[0] = 2 * (-zq * dR[1] + y * dR[2] + zq * dR[3] - x * dR[5] - y * dR[6] + x * dR[7]);
    dqn[1] = 2 * (y * dR[1] + zq * dR[2] + y * dR[3] - 2 * x * dR[4] - w * dR[5] + zq * dR[6] + w * dR[7] - 2 * x * dR[8]);
    dqn[2] = 2 * (-2 * y * dR[0] + x * dR[1] + w * dR[2] + x * dR[3] + zq * dR[5] - w * dR[6] + zq * dR[7] - 2 * y * dR[8]);
    dqn[3] = 2 * (-2 * zq * dR[0] - w * dR[1] + x * dR[2] + w * dR[3] - 2 * zq * dR[4] + y * dR[5] + x * dR[6] + y * dR[7]);
    const scalar_t proj = dqn[0] * w + dqn[1] * x + dqn[2] * y + dqn[3] * zq;
    for (int k = 0; k < 4; ++k) d_quats[4 * i + k] = (dqn[k] - g.qn[k] * proj) * g.qinv;
    // JW = J W
    scalar_t dJ[6];
    for (int r = 0; r < 2; ++r)
      for (int k = 0; k < 3; ++k)
        dJ[3 * r + k] = dJW[3 * r] * cam.W[3 * k] + dJW[3 * r + 1] * cam.W[3 * k + 1] + dJW[3 * r + 2] * cam.W[3 * k + 2];
    // J = [[fx/z, 0, -fx xz/z], [0, fy/z, -fy yz/z]]
    const scalar_t iz = scalar_t(1) / g.z;
    dz -= (dJ[0] * cam.fx + dJ[4] * cam.fy) * iz * iz;
    dz += (dJ[2] * cam.fx * g.xz + dJ[5] * cam.fy * g.yz) * iz * iz;
    const scalar_t dxz = -dJ[2] * cam.fx * iz, dyz = -dJ[5] * cam.fy * iz;
    if (!g.clamp_x) {  // xz = p_x / z
      dp[0] += dxz * iz;
      dz -= dxz * g.p[0] * iz * iz;
    }
    if (!g.clamp_y) {
      dp[1] += dyz * iz;
      dz -= dyz * g.p[1] * iz * iz;
    }
    if (g.depth_ok) dp[2] += dz;
    // p = W m + t
    for (int k = 0; k < 3; ++k) d_means[3 * i + k] = cam.W[k] * dp[0] + cam.W[3 + k] * dp[1] + cam.W[6 + k] * dp[2];
  }
}

template <typename scalar_t>
Camera<scalar_t> make_camera(const at::Tensor& viewmat, const at::Tensor& K, int64_t width, int64_t height,
                             double near, double far, double eps2d, double sigma_radius, double guard_band,
                             bool antialiased) {
  double v[16], k[9];
  eg::read_doubles(viewmat, v, 16);
  eg::read_doubles(K, k, 9);
  Camera<scalar_t> cam;
  for (int r = 0; r < 3; ++r) {
    for (int c = 0; c < 3; ++c) cam.W[3 * r + c] = scalar_t(v[4 * r + c]);
    cam.t[r] = scalar_t(v[4 * r + 3]);
  }
  cam.fx = scalar_t(k[0]);
  cam.fy = scalar_t(k[4]);
  cam.cx = scalar_t(k[2]);
  cam.cy = scalar_t(k[5]);
  // limits computed in the dtype of the means, as the torch code does
  const scalar_t tan_x = scalar_t(0.5) * scalar_t(width) / cam.fx, tan_y = scalar_t(0.5) * scalar_t(height) / cam.fy;
  cam.lim_x_neg = cam.cx / cam.fx + scalar_t(guard_band) * tan_x;
  cam.lim_x_pos = (scalar_t(width) - cam.cx) / cam.fx + scalar_t(guard_band) * tan_x;
  cam.lim_y_neg = cam.cy / cam.fy + scalar_t(guard_band) * tan_y;
  cam.lim_y_pos = (scalar_t(height) - cam.cy) / cam.fy + scalar_t(guard_band) * tan_y;
  cam.near = scalar_t(near);
  cam.far = scalar_t(far);
  cam.eps2d = scalar_t(eps2d);
  cam.sigma_radius = scalar_t(sigma_radius);
  cam.width = width;
  cam.height = height;
  cam.antialiased = antialiased;
  return cam;
}

}  // namespace

// (means2d [N,2], conics [N,3], opacities [N], depths [N], radii [N,2] int32, support [N,2], visible [N] bool)
std::vector<at::Tensor> project_forward(at::Tensor means, at::Tensor quats, at::Tensor scales,
                                           at::Tensor opacities, at::Tensor viewmat, at::Tensor K,
                                           int64_t width, int64_t height, double near, double far, double eps2d,
                                           double sigma_radius, double guard_band, bool antialiased, double alpha_min,
                                           int64_t threads) {
  for (const auto* t : {&means, &quats, &scales, &opacities}) {
    TORCH_CHECK(t->device().is_cpu() && t->is_contiguous(), "project_cpu: CPU contiguous tensors");
    TORCH_CHECK(t->scalar_type() == means.scalar_type(), "project_cpu: tensors must share one dtype");
  }
  const int64_t n = means.size(0);
  const auto dtype = means.scalar_type();
  auto means2d = eg::empty_cpu({n, 2}, dtype), conics = eg::empty_cpu({n, 3}, dtype), opac = eg::empty_cpu({n}, dtype);
  auto depths = eg::empty_cpu({n}, dtype), support = eg::empty_cpu({n, 2}, dtype);
  auto radii = eg::empty_cpu({n, 2}, at::kInt), visible = eg::empty_cpu({n}, at::kBool);
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "project_forward", [&] {
    const auto cam = make_camera<scalar_t>(viewmat, K, width, height, near, far, eps2d, sigma_radius, guard_band,
                                           antialiased);
    project_forward_impl<scalar_t>(cam, n, means.data_ptr<scalar_t>(), quats.data_ptr<scalar_t>(),
                                   scales.data_ptr<scalar_t>(), opacities.data_ptr<scalar_t>(),
                                   means2d.data_ptr<scalar_t>(), conics.data_ptr<scalar_t>(), opac.data_ptr<scalar_t>(),
                                   depths.data_ptr<scalar_t>(), radii.data_ptr<int32_t>(),
                                   support.data_ptr<scalar_t>(), visible.data_ptr<bool>(), scalar_t(alpha_min),
                                   threads);
  });
  return {means2d, conics, opac, depths, radii, support, visible};
}

// (d means [N,3], d quats [N,4], d scales [N,3], d opacities [N])
std::vector<at::Tensor> project_backward(at::Tensor means, at::Tensor quats, at::Tensor scales,
                                            at::Tensor opacities, at::Tensor viewmat, at::Tensor K,
                                            int64_t width, int64_t height, double near, double far, double eps2d,
                                            double sigma_radius, double guard_band, bool antialiased,
                                            at::Tensor g_means2d, at::Tensor g_conics, at::Tensor g_opac,
                                            at::Tensor g_depths, int64_t threads) {
  const int64_t n = means.size(0);
  g_means2d = eg::rows_of(g_means2d), g_conics = eg::rows_of(g_conics);
  const RowStrides gs{g_means2d.stride(0), g_conics.stride(0), g_opac.stride(0), g_depths.stride(0)};
  const auto dtype = means.scalar_type();
  auto d_means = eg::empty_cpu({n, 3}, dtype), d_quats = eg::empty_cpu({n, 4}, dtype);
  auto d_scales = eg::empty_cpu({n, 3}, dtype), d_opac = eg::empty_cpu({n}, dtype);
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "project_backward", [&] {
    const auto cam = make_camera<scalar_t>(viewmat, K, width, height, near, far, eps2d, sigma_radius, guard_band,
                                           antialiased);
    project_backward_impl<scalar_t>(
        cam, n, means.data_ptr<scalar_t>(), quats.data_ptr<scalar_t>(), scales.data_ptr<scalar_t>(),
        opacities.data_ptr<scalar_t>(), g_means2d.data_ptr<scalar_t>(), g_conics.data_ptr<scalar_t>(),
        g_opac.data_ptr<scalar_t>(), g_depths.data_ptr<scalar_t>(), gs, d_means.data_ptr<scalar_t>(),
        d_quats.data_ptr<scalar_t>(), d_scales.data_ptr<scalar_t>(), d_opac.data_ptr<scalar_t>(), threads);
  });
  return {d_means, d_quats, d_scales, d_opac};
}
