// SH colours on the CPU, forward and backward: exploregs_plugin/rasterizer/sh.py as one loop over the
// visible Gaussians. colour = max(sum_b Y_b(d) k_b + 0.5, 0) along d = (m - camera) / |m - camera|
// (|m - camera|^2 floored at 1e-30), real SH up to degree 3 with the constants of sh.py.
// Each visible Gaussian writes only its own rows: the result does not depend on the thread count.

// ATen's tensor headers only (outputs made through tensors.h): the whole of torch/extension.h
// costs about five times the CPU time to compile (docs/training.md, "Building the kernels").
#include "tensors.h"
#include <ATen/Dispatch.h>
#include <ATen/core/Tensor.h>

#include <omp.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <vector>

namespace {

constexpr double C0 = 0.28209479177387814, C1 = 0.4886025119029199;
constexpr double C2[5] = {1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792,
                          0.5462742152960396};
constexpr double C3[7] = {-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
                          -0.4570457994644658, 1.445305721320277, -0.5900435899266435};
constexpr double NORM2_MIN = 1e-30;

// Basis values Y_b(x, y, z) for b < (degree + 1)^2 and, with grad, their derivatives (dY/dx, dY/dy, dY/dz).
template <typename scalar_t>
inline void basis(scalar_t x, scalar_t y, scalar_t z, int degree, scalar_t* Y, scalar_t (*dY)[3]) {
  using S = scalar_t;
  Y[0] = S(C0);
  if (dY) dY[0][0] = dY[0][1] = dY[0][2] = 0;
  if (degree < 1) return;
  Y[1] = -S(C1) * y;
  Y[2] = S(C1) * z;
  Y[3] = -S(C1) * x;
  if (dY) {
    for (int b = 1; b < 4; ++b) dY[b][0] = dY[b][1] = dY[b][2] = 0;
    dY[1][1] = -S(C1);
    dY[2][2] = S(C1);
    dY[3][0] = -S(C1);
  }
  if (degree < 2) return;
  const S xx = x * x, yy = y * y, zz = z * z;
  Y[4] = S(C2[0]) * x * y;
  Y[5] = S(C2[1]) * y * z;
  Y[6] = S(C2[2]) * (S(2) * zz - xx - yy);
  Y[7] = S(C2[3]) * x * z;
  Y[8] = S(C2[4]) * (xx - yy);
  if (dY) {
    const S d[5][3] = {{y, x, 0}, {0, z, y}, {-2 * x, -2 * y, 4 * z}, {z, 0, x}, {2 * x, -2 * y, 0}};
    for (int b = 0; b < 5; ++b)
      for (int k = 0; k < 3; ++k) dY[4 + b][k] = S(C2[b]) * d[b][k];
  }
  if (degree < 3) return;
  Y[9] = S(C3[0]) * y * (S(3) * xx - yy);
  Y[10] = S(C3[1]) * x * y * z;
  Y[11] = S(C3[2]) * y * (S(4) * zz - xx - yy);
  Y[12] = S(C3[3]) * z * (S(2) * zz - S(3) * xx - S(3) * yy);
  Y[13] = S(C3[4]) * x * (S(4) * zz - xx - yy);
  Y[14] = S(C3[5]) * z * (xx - yy);
  Y[15] = S(C3[6]) * x * (xx - S(3) * yy);
  if (dY) {
    const S d[7][3] = {
        {6 * x * y, 3 * xx - 3 * yy, 0},
        {y * z, x * z, x * y},
        {-2 * x * y, 4 * zz - xx - 3 * yy, 8 * y * z},
        {-6 * x * z, -6 * y * z, 6 * zz - 3 * xx - 3 * yy},
        {4 * zz - 3 * xx - yy, -2 * x * y, 8 * x * z},
        {2 * x * z, -2 * y * z, xx - yy},
        {3 * xx - 3 * yy, -6 * x * y, 0},
    };
    for (int b = 0; b < 7; ++b)
      for (int k = 0; k < 3; ++k) dY[9 + b][k] = S(C3[b]) * d[b][k];
  }
}

// Unit direction from the camera centre and 1 / |m - camera| (the floored norm).
template <typename scalar_t>
inline void direction(const scalar_t* m, const scalar_t* cam, scalar_t* d, scalar_t& inv, bool& floored) {
  scalar_t v[3] = {m[0] - cam[0], m[1] - cam[1], m[2] - cam[2]};
  const scalar_t n2 = v[0] * v[0] + v[1] * v[1] + v[2] * v[2];
  floored = !(n2 > scalar_t(NORM2_MIN));
  inv = scalar_t(1) / std::sqrt(floored ? scalar_t(NORM2_MIN) : n2);
  for (int k = 0; k < 3; ++k) d[k] = v[k] * inv;
}

// The coefficients are two tensors, as the model keeps them: sh0 [N, 1, 3] (the base colour) and
// shN [N, K - 1, 3] (the higher bands): row g's coefficient b is sh0's for b = 0, shN's b - 1 after.
// Reading them where they are spares the [N, K, 3] concatenation and, in the backward, the copies
// of its gradient's two slices into each parameter's gradient.
template <typename scalar_t>
inline void gather_coeffs(const scalar_t* sh0, const scalar_t* shN, int64_t g, int64_t n_rest, int nb, scalar_t* k) {
  for (int c = 0; c < 3; ++c) k[c] = sh0[3 * g + c];
  const scalar_t* rest = shN + g * n_rest * 3;
  for (int b = 1; b < nb; ++b)
    for (int c = 0; c < 3; ++c) k[3 * b + c] = rest[3 * (b - 1) + c];
}

template <typename scalar_t>
void sh_forward_impl(int64_t n, const bool* visible, const scalar_t* sh0, const scalar_t* shN, const scalar_t* means,
                     const scalar_t* cam, int64_t n_rest, int degree, scalar_t* colors, int64_t threads) {
  const int nb = (degree + 1) * (degree + 1);
#pragma omp parallel for num_threads(std::max<int64_t>(1, threads)) schedule(static)
  for (int64_t g = 0; g < n; ++g) {
    if (!visible[g]) continue;  // its colour stays 0: the compositor never reads it
    scalar_t d[3], inv, Y[16];
    bool floored;
    direction(means + 3 * g, cam, d, inv, floored);
    basis<scalar_t>(d[0], d[1], d[2], degree, Y, nullptr);
    scalar_t k[48];
    gather_coeffs(sh0, shN, g, n_rest, nb, k);
    for (int c = 0; c < 3; ++c) {
      scalar_t v = 0;
      for (int b = 0; b < nb; ++b) v += Y[b] * k[3 * b + c];
      colors[3 * g + c] = std::max(v + scalar_t(0.5), scalar_t(0));
    }
  }
}

template <typename scalar_t>
void sh_backward_impl(int64_t n, const bool* visible, const scalar_t* sh0, const scalar_t* shN, const scalar_t* means,
                      const scalar_t* cam, int64_t n_rest, int degree, const scalar_t* g_colors,
                      int64_t g_stride, scalar_t* d_sh0, scalar_t* d_shN, scalar_t* d_means, int64_t threads) {
  const int nb = (degree + 1) * (degree + 1);
#pragma omp parallel for num_threads(std::max<int64_t>(1, threads)) schedule(static)
  for (int64_t g = 0; g < n; ++g) {
    if (!visible[g]) continue;
    scalar_t d[3], inv, Y[16], dY[16][3];
    bool floored;
    direction(means + 3 * g, cam, d, inv, floored);
    basis<scalar_t>(d[0], d[1], d[2], degree, Y, dY);
    scalar_t k[48];
    gather_coeffs(sh0, shN, g, n_rest, nb, k);
    scalar_t gc[3];
    for (int c = 0; c < 3; ++c) {  // the clamp at 0 passes the gradient where SH + 0.5 >= 0
      scalar_t v = 0;
      for (int b = 0; b < nb; ++b) v += Y[b] * k[3 * b + c];
      gc[c] = v + scalar_t(0.5) >= scalar_t(0) ? g_colors[g * g_stride + c] : scalar_t(0);
    }
    scalar_t* d_rest = d_shN + g * n_rest * 3;
    scalar_t dd[3] = {0, 0, 0};
    for (int b = 0; b < nb; ++b) {
      scalar_t* dk = b == 0 ? d_sh0 + 3 * g : d_rest + 3 * (b - 1);
      scalar_t kb = 0;
      for (int c = 0; c < 3; ++c) {
        dk[c] = Y[b] * gc[c];
        kb += k[3 * b + c] * gc[c];
      }
      for (int q = 0; q < 3; ++q) dd[q] += dY[b][q] * kb;
    }
    // d = v inv: dd/dv = inv (I - d d^T), or inv I where the norm is floored
    const scalar_t proj = floored ? scalar_t(0) : d[0] * dd[0] + d[1] * dd[1] + d[2] * dd[2];
    for (int q = 0; q < 3; ++q) d_means[3 * g + q] = (dd[q] - d[q] * proj) * inv;
  }
}

// The camera centre [3] in the means' dtype (rounded as a .to() would round it).
template <typename scalar_t>
std::array<scalar_t, 3> camera_in(const at::Tensor& camera) {
  double c[3];
  eg::read_doubles(camera, c, 3);
  return {scalar_t(c[0]), scalar_t(c[1]), scalar_t(c[2])};
}

}  // namespace

// colours [N, 3] of the coefficients sh0 [N, 1, 3] and shN [N, K - 1, 3] and the means [N, 3] seen
// from `camera` [3], for the rows where `visible` [N] (bool) holds, 0 elsewhere: the compositor
// reads the visible rows of full-size tensors, so no gather of the visible rows is made before it
// (nor its backward's scatter).
at::Tensor sh_forward(at::Tensor sh0, at::Tensor shN, at::Tensor means, at::Tensor visible, at::Tensor camera,
                         int64_t degree, int64_t threads) {
  TORCH_CHECK(sh0.is_contiguous() && shN.is_contiguous() && means.is_contiguous() && visible.is_contiguous(),
              "sh_cpu: contiguous");
  TORCH_CHECK(visible.scalar_type() == at::kBool && visible.numel() == means.size(0), "sh_cpu: one bool per row");
  TORCH_CHECK(sh0.size(0) == means.size(0) && shN.size(0) == means.size(0) && sh0.size(1) == 1 && sh0.size(2) == 3 &&
                  shN.size(2) == 3, "sh_cpu: sh0 [N, 1, 3] and shN [N, K - 1, 3]");
  TORCH_CHECK(degree >= 0 && degree <= 3 && 1 + shN.size(1) >= (degree + 1) * (degree + 1), "sh_cpu: degree");
  const int64_t n = means.size(0);
  auto colors = eg::zeros_cpu({n, 3}, means.scalar_type());
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "sh_forward", [&] {
    const auto cam = camera_in<scalar_t>(camera);
    sh_forward_impl<scalar_t>(n, visible.data_ptr<bool>(), sh0.data_ptr<scalar_t>(), shN.data_ptr<scalar_t>(),
                              means.data_ptr<scalar_t>(), cam.data(), shN.size(1), static_cast<int>(degree),
                              colors.data_ptr<scalar_t>(), threads);
  });
  return colors;
}

// (d sh0 [N, 1, 3], d shN [N, K - 1, 3], d means [N, 3]) from d colours [N, 3]: zero for the rows
// not visible; each the shape and layout of its parameter, so autograd takes it as the gradient
// as it is.
std::vector<at::Tensor> sh_backward(at::Tensor sh0, at::Tensor shN, at::Tensor means, at::Tensor visible,
                                       at::Tensor camera, int64_t degree, at::Tensor g_colors, int64_t threads) {
  TORCH_CHECK(g_colors.size(0) == means.size(0), "sh_cpu: one gradient row each");
  // the compositor's backward hands the colours' gradient over as columns of one block: its rows
  // are read where they are
  g_colors = eg::rows_of(g_colors);
  auto d_sh0 = eg::zeros_cpu(sh0.sizes(), sh0.scalar_type()), d_shN = eg::zeros_cpu(shN.sizes(), shN.scalar_type());
  auto d_means = eg::zeros_cpu(means.sizes(), means.scalar_type());
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "sh_backward", [&] {
    const auto cam = camera_in<scalar_t>(camera);
    sh_backward_impl<scalar_t>(means.size(0), visible.data_ptr<bool>(), sh0.data_ptr<scalar_t>(),
                               shN.data_ptr<scalar_t>(), means.data_ptr<scalar_t>(), cam.data(), shN.size(1),
                               static_cast<int>(degree), g_colors.data_ptr<scalar_t>(), g_colors.stride(0),
                               d_sh0.data_ptr<scalar_t>(), d_shN.data_ptr<scalar_t>(), d_means.data_ptr<scalar_t>(),
                               threads);
  });
  return {d_sh0, d_shN, d_means};
}
