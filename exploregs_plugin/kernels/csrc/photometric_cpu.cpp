// 3DGS's training loss on the CPU, forward and backward in one kernel each:
//   L = (1 - lambda) mean|x - y| + lambda (1 - mean S),
// S the SSIM map of exploregs_plugin/model/losses.py's ssim_map (11 x 11 Gaussian window, sigma
// 1.5, separable, zero padding, per channel). Images are the renderer's [H, W, C] as they are: the
// kernel copies them into [C, H, W] planes itself (no torch operator for a permute and a copy, and
// the filters run on contiguous rows), and the backward writes [H, W, C].
//
// With G the window, mu_x = G * x, mu_y = G * y, e_xx = G * x^2, e_yy = G * y^2, e_xy = G * (x y):
//   A1 = 2 mu_x mu_y + C1, A2 = 2 (e_xy - mu_x mu_y) + C2,
//   B1 = mu_x^2 + mu_y^2 + C1, B2 = (e_xx - mu_x^2) + (e_yy - mu_y^2) + C2, S = A1 A2 / (B1 B2).
// Backward (y fixed), with s = dL/dS = -lambda g / N the same at every pixel (N = H W C):
//   dS/dmu_x = 2 mu_y (A2 - A1) / (B1 B2) - 2 mu_x S (B2 - B1) / (B1 B2),
//   dS/de_xx = -S / B2, dS/de_xy = 2 A1 / (B1 B2),
//   dL/dx = G * (s dS/dmu_x) + 2 x G * (s dS/de_xx) + y G * (s dS/de_xy) + (1 - lambda) g / N sgn(x - y)
// (the window is symmetric, so the adjoint of the zero-padded filter is the same filter; sgn(0) =
// 0, as torch's abs). B1 >= C1 and B2 >= C2 - rounding > 0, so the divisions are safe.
//
// Determinism: each plane is filtered by one thread in a fixed order, and the means are sums per
// image row (in double, in eight fixed lanes) added in row order after the parallel loop: the same
// bits at any thread count.

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

// Separable filter of one [H, W] plane with zero padding: rows first, then columns. Each output
// is added up in registers over the taps in ascending order (the taps that fall outside the plane
// skipped), BLOCK pixels at a time: the same operations in the same order as a pass over the whole
// row per tap, so the same bits, without storing and reloading the row after every tap (1.4x
// faster at 176 x 315 in float32, 1.8x at 533 x 800; 32 pixels are four AVX2 vectors).
template <typename scalar_t>
void blur(const scalar_t* in, scalar_t* out, scalar_t* tmp, int64_t h, int64_t w, const scalar_t* g) {
  constexpr int64_t BLOCK = 32, TAPS = 2 * RADIUS + 1;
  for (int64_t y = 0; y < h; ++y) {
    const scalar_t* row = in + y * w;
    scalar_t* t = tmp + y * w;
    auto edge = [&](int64_t x) {  // a pixel within RADIUS of the row's ends, or past the last block
      scalar_t acc = 0;
      for (int64_t k = 0; k < TAPS; ++k) {
        const int64_t xs = x + k - RADIUS;
        if (xs >= 0 && xs < w) acc += g[k] * row[xs];
      }
      t[x] = acc;
    };
    const int64_t inner0 = std::min<int64_t>(RADIUS, w), inner1 = std::max<int64_t>(inner0, w - RADIUS);
    for (int64_t x = 0; x < inner0; ++x) edge(x);
    int64_t x = inner0;
    for (; x + BLOCK <= inner1; x += BLOCK) {  // every tap inside the row
      scalar_t acc[BLOCK] = {};
      for (int64_t k = 0; k < TAPS; ++k) {
        const scalar_t gk = g[k];
        const scalar_t* r = row + x + k - RADIUS;
        for (int64_t l = 0; l < BLOCK; ++l) acc[l] += gk * r[l];
      }
      for (int64_t l = 0; l < BLOCK; ++l) t[x + l] = acc[l];
    }
    for (; x < w; ++x) edge(x);
  }
  for (int64_t y = 0; y < h; ++y) {
    scalar_t* o = out + y * w;
    const int64_t k0 = std::max<int64_t>(0, RADIUS - y), k1 = std::min<int64_t>(2 * RADIUS, h - 1 - y + RADIUS);
    int64_t x = 0;
    for (; x + BLOCK <= w; x += BLOCK) {
      scalar_t acc[BLOCK] = {};
      for (int64_t k = k0; k <= k1; ++k) {
        const scalar_t gk = g[k];
        const scalar_t* t = tmp + (y + k - RADIUS) * w + x;
        for (int64_t l = 0; l < BLOCK; ++l) acc[l] += gk * t[l];
      }
      for (int64_t l = 0; l < BLOCK; ++l) o[x + l] = acc[l];
    }
    for (; x < w; ++x) {
      scalar_t acc = 0;
      for (int64_t k = k0; k <= k1; ++k) acc += g[k] * tmp[(y + k - RADIUS) * w + x];
      o[x] = acc;
    }
  }
}

template <typename scalar_t>
scalar_t sgn(scalar_t v) {
  return v > 0 ? scalar_t(1) : v < 0 ? scalar_t(-1) : scalar_t(0);
}

constexpr int LANES = 8;

// Sum of v[0..n) in double, in a fixed order that vectorises: lane l adds v[l], v[l + 8], ...,
// then the lanes are added in order (a plain running sum cannot vectorise without reordering).
template <typename scalar_t>
double lane_sum(const scalar_t* v, int64_t n) {
  double lanes[LANES] = {0, 0, 0, 0, 0, 0, 0, 0};
  int64_t j = 0;
  for (; j + LANES <= n; j += LANES)
    for (int l = 0; l < LANES; ++l) lanes[l] += double(v[j + l]);
  for (int l = 0; j < n; ++j, ++l) lanes[l] += double(v[j]);
  double sum = 0;
  for (int l = 0; l < LANES; ++l) sum += lanes[l];
  return sum;
}

// [H, W, C] -> [C, H, W] planes (the filters and the per-pixel loops then run on contiguous rows).
template <typename scalar_t>
void to_planes(const scalar_t* hwc, scalar_t* planes, int64_t c, int64_t hw) {
  for (int64_t j = 0; j < hw; ++j)
    for (int64_t ch = 0; ch < c; ++ch) planes[ch * hw + j] = hwc[j * c + ch];
}

// x, y: [C, H, W] planes; mom: [5, C, H, W]; rows: [C H, 3] per-row sums of |x - y|, S and (x - y)^2.
template <typename scalar_t>
void forward_impl(const scalar_t* x, const scalar_t* y, scalar_t* mom, double* rows, int64_t c, int64_t h,
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
    std::vector<scalar_t> ssim_row(w), l1_row(w);
    std::vector<double> squared_row(w);
#pragma omp for schedule(static)
    for (int64_t row = 0; row < c * h; ++row) {  // row = channel * h + image row: the planes' rows in order
      const int64_t first = row * w;
      for (int64_t k = 0; k < w; ++k) {
        const int64_t i = first + k;
        const scalar_t mx = mom[i], my = mom[c * hw + i];
        const scalar_t vx = mom[2 * c * hw + i] - mx * mx, vy = mom[3 * c * hw + i] - my * my;
        const scalar_t cxy = mom[4 * c * hw + i] - mx * my;
        ssim_row[k] = ((2 * mx * my + C1) * (2 * cxy + C2)) / ((mx * mx + my * my + C1) * (vx + vy + C2));
        l1_row[k] = std::abs(x[i] - y[i]);
        const double d = double(x[i]) - double(y[i]);  // the PSNR's error in double, as model.losses.psnr
        squared_row[k] = d * d;
      }
      rows[3 * row] = lane_sum(l1_row.data(), w);
      rows[3 * row + 1] = lane_sum(ssim_row.data(), w);
      rows[3 * row + 2] = lane_sum(squared_row.data(), w);
    }
  }
}

// x, y: [C, H, W] planes; out: [C, H, W].
template <typename scalar_t>
void backward_impl(const scalar_t* x, const scalar_t* y, const scalar_t* mom, scalar_t gs, scalar_t gl, scalar_t* k,
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
      k[i] = gs * (2 * my * (a2 - a1) * inv - 2 * mx * s * (b2 - b1) * inv);
      k[c * hw + i] = gs * (-s / b2);
      k[2 * c * hw + i] = gs * (2 * a1 * inv);
    }
    std::vector<scalar_t> tmp(hw);
#pragma omp for schedule(static)
    for (int64_t plane = 0; plane < 3 * c; ++plane) blur(k + plane * hw, f + plane * hw, tmp.data(), h, w, g.data());
#pragma omp for schedule(static)
    for (int64_t i = 0; i < c * hw; ++i)
      out[i] = f[i] + 2 * x[i] * f[c * hw + i] + y[i] * f[2 * c * hw + i] + gl * sgn(x[i] - y[i]);
  }
}

}  // namespace

// img, ref: [H, W, C] contiguous, one shape and dtype. Returns (the loss, mean |img - ref|,
// 1 - mean SSIM: 0-dim tensors of img's dtype; the PSNR of img against ref in dB, -10 log10(max(MSE,
// mse_floor)), a 0-dim float64 tensor (the training step's logged PSNR, for nothing more than one
// more sum); the means summed in double; moments [7, C, H, W]: mu_x, mu_y, e_xx, e_yy, e_xy, img,
// ref as planes, kept for the backward).
std::vector<at::Tensor> photometric_forward(at::Tensor img, at::Tensor ref, double lambda, double c1, double c2,
                                            double mse_floor, int64_t threads) {
  TORCH_CHECK(img.is_contiguous() && ref.is_contiguous() && img.sizes() == ref.sizes() && img.dim() == 3 &&
                  img.scalar_type() == ref.scalar_type(),
              "photometric_cpu: img and ref must be contiguous [H, W, C] of one shape and dtype");
  const int64_t h = img.size(0), w = img.size(1), c = img.size(2);
  // moments [7, C, H, W]: the five moments, then img and ref as planes (the backward reads them)
  auto moments = eg::empty_cpu({7, c, h, w}, img.scalar_type());
  auto loss = eg::empty_cpu({}, img.scalar_type()), l1 = eg::empty_cpu({}, img.scalar_type());
  auto dssim = eg::empty_cpu({}, img.scalar_type());
  auto psnr = eg::empty_cpu({}, at::kDouble);
  std::vector<double> rows(3 * c * h);
  AT_DISPATCH_FLOATING_TYPES(img.scalar_type(), "photometric_forward", [&] {
    scalar_t* mom = moments.data_ptr<scalar_t>();
    scalar_t *x = mom + 5 * c * h * w, *y = mom + 6 * c * h * w;
    to_planes(img.data_ptr<scalar_t>(), x, c, h * w);
    to_planes(ref.data_ptr<scalar_t>(), y, c, h * w);
    forward_impl<scalar_t>(x, y, mom, rows.data(), c, h, w, scalar_t(c1), scalar_t(c2), threads);
    double l1_sum = 0, s_sum = 0, squared_sum = 0;
    for (int64_t row = 0; row < c * h; ++row) {  // row order, whatever the threads
      l1_sum += rows[3 * row];
      s_sum += rows[3 * row + 1];
      squared_sum += rows[3 * row + 2];
    }
    const double n = double(std::max<int64_t>(1, c * h * w)), l1_mean = l1_sum / n, dssim_mean = 1.0 - s_sum / n;
    *loss.data_ptr<scalar_t>() = scalar_t((1.0 - lambda) * l1_mean + lambda * dssim_mean);
    *l1.data_ptr<scalar_t>() = scalar_t(l1_mean);
    *dssim.data_ptr<scalar_t>() = scalar_t(dssim_mean);
    *psnr.data_ptr<double>() = -10.0 * std::log10(std::max(squared_sum / n, mse_floor));
  });
  return {loss, l1, dssim, psnr, moments};
}

// dL/dimg [H, W, C] of L = (1 - lambda) mean|img - ref| + lambda (1 - mean SSIM), times grad_loss
// (a one-element tensor of img's dtype, read here: no operator to turn it into a number).
at::Tensor photometric_backward(at::Tensor moments, at::Tensor grad_loss, double lambda, double c1, double c2,
                                int64_t threads) {
  TORCH_CHECK(moments.is_contiguous() && moments.dim() == 4 && moments.size(0) == 7,
              "photometric_cpu: moments must be photometric_forward's [7, C, H, W]");
  TORCH_CHECK(grad_loss.numel() == 1 && grad_loss.scalar_type() == moments.scalar_type(),
              "photometric_cpu: grad_loss must be one element of the images' dtype");
  const int64_t c = moments.size(1), h = moments.size(2), w = moments.size(3), hw = h * w;
  const double n = double(std::max<int64_t>(1, c * hw));
  auto work = eg::empty_cpu({7, c, h, w}, moments.scalar_type());  // s dS/dmu_x, s dS/de_xx, s dS/de_xy; filtered; out
  auto grad = eg::empty_cpu({h, w, c}, moments.scalar_type());
  AT_DISPATCH_FLOATING_TYPES(moments.scalar_type(), "photometric_backward", [&] {
    const double g = double(*grad_loss.data_ptr<scalar_t>());
    const scalar_t* mom = moments.data_ptr<scalar_t>();
    scalar_t* k = work.data_ptr<scalar_t>();
    scalar_t* planes = k + 6 * c * hw;
    backward_impl<scalar_t>(mom + 5 * c * hw, mom + 6 * c * hw, mom, scalar_t(-lambda * g / n),
                            scalar_t((1.0 - lambda) * g / n), k, k + 3 * c * hw, planes, c, h, w, scalar_t(c1),
                            scalar_t(c2), threads);
    scalar_t* out = grad.data_ptr<scalar_t>();
    for (int64_t j = 0; j < hw; ++j)
      for (int64_t ch = 0; ch < c; ++ch) out[j * c + ch] = planes[ch * hw + j];
  });
  return grad;
}
