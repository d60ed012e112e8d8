// Fused SSIM on the CPU, forward and backward: exploregs_plugin/model/losses.py's ssim_map with
// an 11 x 11 Gaussian window (sigma 1.5, separable) and zero padding, per channel.
//
// With G the window, mu_x = G * x, mu_y = G * y, e_xx = G * x^2, e_yy = G * y^2, e_xy = G * (x y):
//   A1 = 2 mu_x mu_y + C1, A2 = 2 (e_xy - mu_x mu_y) + C2,
//   B1 = mu_x^2 + mu_y^2 + C1, B2 = (e_xx - mu_x^2) + (e_yy - mu_y^2) + C2, S = A1 A2 / (B1 B2).
// Backward (y fixed), with s = dL/dS per pixel:
//   dS/dmu_x = 2 mu_y (A2 - A1) / (B1 B2) - 2 mu_x S (B2 - B1) / (B1 B2),
//   dS/de_xx = -S / B2, dS/de_xy = 2 A1 / (B1 B2),
//   dL/dx = G * (s dS/dmu_x) + 2 x G * (s dS/de_xx) + y G * (s dS/de_xy)
// (the window is symmetric, so the adjoint of the zero-padded filter is the same filter).
// B1 >= C1 and B2 >= C2 - rounding > 0, so the divisions are safe. Each plane is filtered by one
// thread in a fixed order: the same bits at any thread count.

// ATen's tensor and its few factory functions only: the whole of torch/extension.h costs about
// five times the CPU time to compile (docs/training.md, "Building the kernels").
#include <ATen/Dispatch.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/empty_like.h>
#include <ATen/ops/zeros.h>
#include <ATen/ops/zeros_like.h>

#include <omp.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

namespace {

constexpr int RADIUS = 5;  // 11 taps
constexpr double SIGMA = 1.5;

template <typename scalar_t>
std::vector<scalar_t> window() {
  std::vector<double> g(2 * RADIUS + 1);
  double sum = 0;
  for (int k = -RADIUS; k <= RADIUS; ++k) sum += g[k + RADIUS] = std::exp(-(k * k) / (2.0 * SIGMA * SIGMA));
  std::vector<scalar_t> out(g.size());
  for (size_t k = 0; k < g.size(); ++k) out[k] = scalar_t(g[k] / sum);
  return out;
}

// Separable filter of one [H, W] plane with zero padding: rows first, then columns.
template <typename scalar_t>
void blur(const scalar_t* in, scalar_t* out, scalar_t* tmp, int64_t h, int64_t w, const scalar_t* g) {
  for (int64_t y = 0; y < h; ++y) {  // taps outermost, pixels innermost (vectorised), k ascending per pixel
    const scalar_t* row = in + y * w;
    scalar_t* t = tmp + y * w;
    for (int64_t x = 0; x < w; ++x) t[x] = 0;
    for (int64_t k = 0; k <= 2 * RADIUS; ++k) {
      const int64_t shift = k - RADIUS, x0 = std::max<int64_t>(0, -shift), x1 = std::min<int64_t>(w, w - shift);
      const scalar_t gk = g[k];
      for (int64_t x = x0; x < x1; ++x) t[x] += gk * row[x + shift];
    }
  }
  for (int64_t y = 0; y < h; ++y) {
    scalar_t* o = out + y * w;
    for (int64_t x = 0; x < w; ++x) o[x] = 0;
    const int64_t k0 = std::max<int64_t>(0, RADIUS - y), k1 = std::min<int64_t>(2 * RADIUS, h - 1 - y + RADIUS);
    for (int64_t k = k0; k <= k1; ++k) {
      const scalar_t gk = g[k];
      const scalar_t* t = tmp + (y + k - RADIUS) * w;
      for (int64_t x = 0; x < w; ++x) o[x] += gk * t[x];
    }
  }
}

template <typename scalar_t>
void ssim_forward_impl(const scalar_t* x, const scalar_t* y, scalar_t* mom, scalar_t* s, int64_t c, int64_t h,
                       int64_t w, scalar_t C1, scalar_t C2, int64_t threads) {
  const int64_t hw = h * w;
  const auto g = window<scalar_t>();
#pragma omp parallel num_threads(std::max<int64_t>(1, std::min(threads, 5 * c)))
  {
    std::vector<scalar_t> src(hw), tmp(hw);
#pragma omp for schedule(static)
    for (int64_t plane = 0; plane < 5 * c; ++plane) {  // plane = moment * c + channel
      const int64_t kind = plane / c, ch = plane % c;
      const scalar_t* a = x + ch * hw;
      const scalar_t* b = y + ch * hw;
      for (int64_t i = 0; i < hw; ++i)
        src[i] = kind == 0 ? a[i] : kind == 1 ? b[i] : kind == 2 ? a[i] * a[i] : kind == 3 ? b[i] * b[i] : a[i] * b[i];
      blur(src.data(), mom + plane * hw, tmp.data(), h, w, g.data());
    }
#pragma omp for schedule(static)
    for (int64_t i = 0; i < c * hw; ++i) {
      const scalar_t mx = mom[i], my = mom[c * hw + i];
      const scalar_t vx = mom[2 * c * hw + i] - mx * mx, vy = mom[3 * c * hw + i] - my * my;
      const scalar_t cxy = mom[4 * c * hw + i] - mx * my;
      s[i] = ((2 * mx * my + C1) * (2 * cxy + C2)) / ((mx * mx + my * my + C1) * (vx + vy + C2));
    }
  }
}

template <typename scalar_t>
void ssim_backward_impl(const scalar_t* x, const scalar_t* y, const scalar_t* mom, const scalar_t* gs, scalar_t* k,
                        scalar_t* f, scalar_t* out, int64_t c, int64_t h, int64_t w, scalar_t C1, scalar_t C2,
                        int64_t threads) {
  const int64_t hw = h * w;
  const auto g = window<scalar_t>();
#pragma omp parallel num_threads(std::max<int64_t>(1, std::min(threads, 3 * c)))
  {
#pragma omp for schedule(static)
    for (int64_t i = 0; i < c * hw; ++i) {
      const scalar_t mx = mom[i], my = mom[c * hw + i];
      const scalar_t vx = mom[2 * c * hw + i] - mx * mx, vy = mom[3 * c * hw + i] - my * my;
      const scalar_t cxy = mom[4 * c * hw + i] - mx * my;
      const scalar_t a1 = 2 * mx * my + C1, a2 = 2 * cxy + C2, b1 = mx * mx + my * my + C1, b2 = vx + vy + C2;
      const scalar_t inv = scalar_t(1) / (b1 * b2), s = a1 * a2 * inv;
      k[i] = gs[i] * (2 * my * (a2 - a1) * inv - 2 * mx * s * (b2 - b1) * inv);
      k[c * hw + i] = gs[i] * (-s / b2);
      k[2 * c * hw + i] = gs[i] * (2 * a1 * inv);
    }
    std::vector<scalar_t> tmp(hw);
#pragma omp for schedule(static)
    for (int64_t plane = 0; plane < 3 * c; ++plane) blur(k + plane * hw, f + plane * hw, tmp.data(), h, w, g.data());
#pragma omp for schedule(static)
    for (int64_t i = 0; i < c * hw; ++i) out[i] = f[i] + 2 * x[i] * f[c * hw + i] + y[i] * f[2 * c * hw + i];
  }
}

}  // namespace

// img, ref: [C, H, W] contiguous. Returns (ssim map [C, H, W], moments [5, C, H, W]: mu_x, mu_y,
// e_xx, e_yy, e_xy, kept for the backward).
std::vector<at::Tensor> ssim_forward(at::Tensor img, at::Tensor ref, double c1, double c2, int64_t threads) {
  TORCH_CHECK(img.is_contiguous() && ref.is_contiguous() && img.sizes() == ref.sizes() && img.dim() == 3,
              "ssim_cpu: img and ref must be contiguous [C, H, W] of one shape");
  const int64_t c = img.size(0), h = img.size(1), w = img.size(2), hw = h * w;
  auto moments = at::empty({5, c, h, w}, img.options());
  auto map = at::empty({c, h, w}, img.options());
  AT_DISPATCH_FLOATING_TYPES(img.scalar_type(), "ssim_forward", [&] {
    ssim_forward_impl<scalar_t>(img.data_ptr<scalar_t>(), ref.data_ptr<scalar_t>(), moments.data_ptr<scalar_t>(),
                                map.data_ptr<scalar_t>(), c, h, w, scalar_t(c1), scalar_t(c2), threads);
  });
  return {map, moments};
}

// dL/dimg [C, H, W] given dL/dS [C, H, W].
at::Tensor ssim_backward(at::Tensor img, at::Tensor ref, at::Tensor moments, at::Tensor grad_map,
                            double c1, double c2, int64_t threads) {
  TORCH_CHECK(grad_map.is_contiguous() && moments.is_contiguous(), "ssim_cpu: contiguous");
  const int64_t c = img.size(0), h = img.size(1), w = img.size(2), hw = h * w;
  auto coef = at::empty({3, c, h, w}, img.options());  // s dS/dmu_x, s dS/de_xx, s dS/de_xy
  auto filtered = at::empty({3, c, h, w}, img.options());
  auto grad = at::empty({c, h, w}, img.options());
  AT_DISPATCH_FLOATING_TYPES(img.scalar_type(), "ssim_backward", [&] {
    ssim_backward_impl<scalar_t>(img.data_ptr<scalar_t>(), ref.data_ptr<scalar_t>(), moments.data_ptr<scalar_t>(),
                                 grad_map.data_ptr<scalar_t>(), coef.data_ptr<scalar_t>(), filtered.data_ptr<scalar_t>(),
                                 grad.data_ptr<scalar_t>(), c, h, w, scalar_t(c1), scalar_t(c2), threads);
  });
  return grad;
}
