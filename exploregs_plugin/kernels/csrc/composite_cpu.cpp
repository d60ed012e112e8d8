// Tile binning and front-to-back alpha compositing of projected Gaussians on the CPU, forward
// and backward: the image model of exploregs_plugin/rasterizer/composite.py, written as loops.
//
// Per pixel, with Gaussians m = 1..n front to back (only pairs whose support box holds the pixel
// centre):
//   alpha_m = min(alpha_max, o_m exp(power_m)),  power_m = -0.5 (a dx^2 + 2 b dx dy + c dy^2),
//   pairs with alpha_m < alpha_min are skipped,
//   T_m = prod_{j<m} (1 - alpha_j); compositing stops before the first m with T_m (1 - alpha_m) < T_min,
//   F = sum_m w_m f_m, w_m = alpha_m T_m (f = features and a last 1 for the alpha A = 1 - T_final).
// Backward, with gf_m = dL/dF . f_m and S_m = sum_{i>m} w_i gf_i = dL/dF . F - sum_{i<=m} w_i gf_i:
//   dL/dalpha_m = T_m gf_m - S_m / (1 - alpha_m)   (1 - alpha_m >= 1 - alpha_max > 0),
//   dL/dpower_m = alpha_m dL/dalpha_m and dL/do_m = exp(power_m) dL/dalpha_m where the clamp is off.
// The backward walks each tile front to back again (the same operations in the same order, so the
// same T_m bit for bit), and keeps nothing per pixel x Gaussian: only the forward's output F.
//
// Determinism: a tile is composited by one thread, in a fixed order, whatever the thread count.
// A Gaussian's gradient is the sum of its per-tile sums, written to one slot per (Gaussian, tile)
// pair and added up in the order the pairs were made (tiles in row-major order), so the result
// is the same bit for bit at any thread count.

// ATen's tensor headers only (outputs made through tensors.h): the whole of torch/extension.h
// costs about five times the CPU time to compile (docs/training.md, "Building the kernels").
#include "tensors.h"
#include <ATen/Dispatch.h>
#include <ATen/core/Tensor.h>

#include <omp.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <optional>
#include <type_traits>
#include <vector>

namespace {

// Pixels are processed in vectors of 32 bytes (8 floats or 4 doubles) with GCC/Clang vector
// extensions: the same operations per lane as a scalar loop (no fused multiply-add, see the
// build flags), so a lane rounds exactly as scalar code would.
template <typename scalar_t>
struct Lanes;
template <>
struct Lanes<float> {
  typedef float V __attribute__((vector_size(32)));
  typedef float VU __attribute__((vector_size(32), aligned(4)));  // unaligned loads and stores
  typedef int32_t M __attribute__((vector_size(32)));              // comparison results: -1 or 0
  static constexpr int N = 8;
};
template <>
struct Lanes<double> {
  typedef double V __attribute__((vector_size(32)));
  typedef double VU __attribute__((vector_size(32), aligned(8)));
  typedef int64_t M __attribute__((vector_size(32)));
  static constexpr int N = 4;
};

template <typename scalar_t>
inline typename Lanes<scalar_t>::V load(const scalar_t* p) {
  return *reinterpret_cast<const typename Lanes<scalar_t>::VU*>(p);
}
template <typename scalar_t>
inline void store(scalar_t* p, typename Lanes<scalar_t>::V v) {
  *reinterpret_cast<typename Lanes<scalar_t>::VU*>(p) = v;
}
template <typename V>
inline V splat(typename std::remove_reference<decltype(V{}[0])>::type x) {
  return V{} + x;
}

// exp of 8 floats: Cody-Waite range reduction and a degree-6 polynomial (about 1 ulp, the Cephes
// coefficients). Arguments below -87 give 0: alpha is then below any alpha_min and the pair is skipped.
inline Lanes<float>::V vexp(Lanes<float>::V x) {
  using V = Lanes<float>::V;
  using M = Lanes<float>::M;
  const M under = x < -87.0f;
  x = x < -87.0f ? splat<V>(-87.0f) : x;
  x = x > 88.0f ? splat<V>(88.0f) : x;
  // round to nearest by the 1.5 * 2^23 trick
  const V n = (x * 1.44269504088896341f + 12582912.0f) - 12582912.0f;
  V r = x - n * 0.693359375f;
  r = r - n * -2.12194440e-4f;
  V p = splat<V>(1.9875691500e-4f);
  p = p * r + 1.3981999507e-3f;
  p = p * r + 8.3334519073e-3f;
  p = p * r + 4.1665795894e-2f;
  p = p * r + 1.6666665459e-1f;
  p = p * r + 5.0000001201e-1f;
  p = p * r * r + r + 1.0f;
  const M bits = (__builtin_convertvector(n, M) + 127) << 23;
  const V scale = reinterpret_cast<const V&>(bits);
  return under ? splat<V>(0.0f) : p * scale;
}

// exp of 4 doubles: the library's (float64 is the accuracy path, not the fast one).
inline Lanes<double>::V vexp(Lanes<double>::V x) {
  Lanes<double>::V r;
  for (int l = 0; l < 4; ++l) r[l] = std::exp(x[l]);
  return r;
}

struct Bins {
  at::Tensor tile_offsets;  // [T + 1] int64: pairs of tile t are [off[t], off[t+1])
  at::Tensor pair_gauss;    // [P] int32: Gaussian row of each pair, front to back inside a tile
  at::Tensor pair_slot;     // [P] int64: the pair's slot in making order (Gaussians by depth, tiles row-major)
  at::Tensor gauss_first;   // [M] int64: first slot of each Gaussian
  at::Tensor gauss_count;   // [M] int64: its number of tiles
};

// Pixel range of one Gaussian: the pixels whose centres may lie inside its support box, widened
// by 1e-3 px so that rounding never drops one (the compositor tests every pixel); its tiles are
// those this range reaches.
template <typename scalar_t>
inline void pixel_rect(scalar_t mx, scalar_t my, scalar_t rx, scalar_t ry, int64_t width, int64_t height,
                       int64_t& x0, int64_t& y0, int64_t& x1, int64_t& y1) {
  auto clampi = [](scalar_t v, int64_t top) -> int64_t {
    v = std::min(std::max(v, scalar_t(0)), scalar_t(top));
    return static_cast<int64_t>(v);
  };
  x0 = clampi(std::ceil(mx - rx - scalar_t(0.5) - scalar_t(1e-3)), width - 1);
  y0 = clampi(std::ceil(my - ry - scalar_t(0.5) - scalar_t(1e-3)), height - 1);
  x1 = clampi(std::floor(mx + rx - scalar_t(0.5) + scalar_t(1e-3)), width - 1);
  y1 = clampi(std::floor(my + ry - scalar_t(0.5) + scalar_t(1e-3)), height - 1);
}

// Unsigned keys that order floats as their values do (IEEE 754: flip every bit of a negative
// value, the sign bit of a positive one); -0.0 sorts before +0.0, which no drawn row has (its depth
// is past the near plane).
inline uint32_t sort_key(float v) {
  uint32_t u;
  std::memcpy(&u, &v, sizeof u);
  return (u & 0x80000000u) ? ~u : (u | 0x80000000u);
}
inline uint64_t sort_key(double v) {
  uint64_t u;
  std::memcpy(&u, &v, sizeof u);
  return (u & 0x8000000000000000ull) ? ~u : (u | 0x8000000000000000ull);
}

// The drawn rows (visible) in order of depth, ties by row: an LSD radix sort of their keys, 8 bits
// a pass, each pass stable, so the order is the stable argsort's of their depths (about a tenth
// of the time of torch.argsort at 20,000 rows, and one operator fewer a view).
template <typename scalar_t>
std::vector<int64_t> depth_order(const scalar_t* depth, const bool* vis, int64_t m) {
  using Key = decltype(sort_key(scalar_t(0)));
  std::vector<int64_t> order, next;
  std::vector<Key> keys, next_keys;
  order.reserve(m);
  for (int64_t g = 0; g < m; ++g)
    if (vis[g]) order.push_back(g);
  const int64_t n = static_cast<int64_t>(order.size());
  keys.resize(n);
  for (int64_t i = 0; i < n; ++i) keys[i] = sort_key(depth[order[i]]);
  next.resize(n);
  next_keys.resize(n);
  for (int shift = 0; shift < int(8 * sizeof(Key)); shift += 8) {
    int64_t count[257] = {};
    for (int64_t i = 0; i < n; ++i) ++count[((keys[i] >> shift) & 0xFF) + 1];
    if (count[((keys.empty() ? Key(0) : keys[0]) >> shift & 0xFF) + 1] == n) continue;  // one bucket: nothing moves
    for (int d = 0; d < 256; ++d) count[d + 1] += count[d];
    for (int64_t i = 0; i < n; ++i) {
      const int64_t at = count[(keys[i] >> shift) & 0xFF]++;
      next[at] = order[i];
      next_keys[at] = keys[i];
    }
    order.swap(next);
    keys.swap(next_keys);
  }
  return order;
}

// Where a Gaussian's alpha can reach alpha_min: pixel centres d (from its mean) with
// q(d) = A dx^2 + 2 B dx dy + C dy^2 <= t = 2 ln(o / alpha_min). A tile of its support box whose
// pixel centres all lie outside that ellipse adds exact zeros to every sum the compositor makes
// (the pair is skipped at each pixel), so it is left out of the bins: the same bits, fewer pairs.
// The test errs to keeping: the smallest q over the rectangle of the tile's centres in the box,
// in double, must exceed t by a margin that covers the compositor's float rounding of q (at most
// a few ulp of each of its terms, which sum to at most 2 kappa q for a condition number kappa of
// the conic) and of exp; a conic that is not positive definite, or too ill-conditioned for that
// bound, keeps the whole box.
struct Ellipse {
  double A, B, C, mx, my, t;  // conic, mean, threshold scaled by the rounding margin
  bool test;                  // false: keep every tile of the box
};

constexpr double CULL_REL_ROUNDING = 2e-6;  // bound of the float rounding of q, per unit of kappa q
constexpr double CULL_MARGIN_Q = 2e-2;      // and an absolute margin on t (exp, o * exp, alpha_min)
constexpr double CULL_KAPPA_MAX = 1e5;      // past this, 2e-6 kappa reaches 0.2: keep the box

template <typename scalar_t>
inline Ellipse ellipse_of(const scalar_t* con, scalar_t opacity, scalar_t alpha_min, scalar_t mx, scalar_t my) {
  const double A = con[0], B = con[1], C = con[2], o = opacity, amin = alpha_min;
  Ellipse e{A, B, C, double(mx), double(my), 0.0, false};
  const double half_sum = 0.5 * (A + C), root = std::sqrt(0.25 * (A - C) * (A - C) + B * B);
  const double lo = half_sum - root, hi = half_sum + root;  // eigenvalues of the conic
  if (!(std::isfinite(A) && std::isfinite(B) && std::isfinite(C) && std::isfinite(o)) || !(lo > 0.0) ||
      !(hi < CULL_KAPPA_MAX * lo))
    return e;
  const double rounding = CULL_REL_ROUNDING * (hi / lo);
  // o <= alpha_min: t <= 0, and only tiles holding q <= margin stay (o exp(-q/2) < alpha_min elsewhere)
  const double t = o > 0.0 ? 2.0 * std::log(o / amin) : -std::numeric_limits<double>::infinity();
  e.t = (std::max(t, 0.0) + CULL_MARGIN_Q) / (1.0 - rounding);
  e.test = true;
  return e;
}

// Smallest q over the rectangle [x0, x1] x [y0, y1] of offsets from the mean (a positive definite
// conic): 0 where it holds the mean, else the least of its four edges' minima (q is convex).
inline double rect_qmin(const Ellipse& e, double x0, double x1, double y0, double y1) {
  if (x0 <= 0.0 && 0.0 <= x1 && y0 <= 0.0 && 0.0 <= y1) return 0.0;
  double best = std::numeric_limits<double>::infinity();
  for (const double y : {y0, y1}) {
    const double x = std::min(std::max(-e.B * y / e.A, x0), x1);
    best = std::min(best, e.A * x * x + 2.0 * e.B * x * y + e.C * y * y);
  }
  for (const double x : {x0, x1}) {
    const double y = std::min(std::max(-e.B * x / e.C, y0), y1);
    best = std::min(best, e.A * x * x + 2.0 * e.B * x * y + e.C * y * y);
  }
  return best;
}

// Whether tile (tx, ty) holds a pixel centre of the box's pixel range [px0, px1] x [py0, py1]
// where the Gaussian may reach alpha_min.
inline bool tile_reached(const Ellipse& e, int64_t tx, int64_t ty, int64_t ts, int64_t px0, int64_t py0,
                         int64_t px1, int64_t py1) {
  if (!e.test) return true;
  const double x0 = double(std::max(tx * ts, px0)) + 0.5 - e.mx, x1 = double(std::min(tx * ts + ts - 1, px1)) + 0.5 - e.mx;
  const double y0 = double(std::max(ty * ts, py0)) + 0.5 - e.my, y1 = double(std::min(ty * ts + ts - 1, py1)) + 0.5 - e.my;
  return rect_qmin(e, x0, x1, y0, y1) <= e.t;
}

// conics and opacities undefined: every tile of the support box (the reference's binning).
template <typename scalar_t>
Bins bin_impl(const at::Tensor& means2d, const at::Tensor& support, const at::Tensor& depths,
              const at::Tensor& visible, const at::Tensor& conics, const at::Tensor& opacities, double alpha_min,
              int64_t width, int64_t height, int64_t ts) {
  const int64_t m = means2d.size(0);
  const int64_t tiles_x = (width + ts - 1) / ts, tiles_y = (height + ts - 1) / ts, n_tiles = tiles_x * tiles_y;
  const auto* mean = means2d.data_ptr<scalar_t>();
  const auto* sup = support.data_ptr<scalar_t>();
  const bool* vis = visible.data_ptr<bool>();
  const bool cull = conics.defined();
  const scalar_t* con = cull ? conics.data_ptr<scalar_t>() : nullptr;
  const scalar_t* opa = cull ? opacities.data_ptr<scalar_t>() : nullptr;
  const std::vector<int64_t> drawn = depth_order<scalar_t>(depths.data_ptr<scalar_t>(), vis, m);
  const int64_t n_drawn = static_cast<int64_t>(drawn.size());
  Bins b;
  b.tile_offsets = eg::zeros_cpu({n_tiles + 1}, at::kLong);
  b.gauss_first = eg::zeros_cpu({m}, at::kLong);  // a row not drawn has no pairs (and a zero gradient)
  b.gauss_count = eg::zeros_cpu({m}, at::kLong);
  auto* off = b.tile_offsets.data_ptr<int64_t>();
  auto* first = b.gauss_first.data_ptr<int64_t>();
  auto* count = b.gauss_count.data_ptr<int64_t>();
  // each drawn row's tiles in making order (row-major), the rows front to back
  std::vector<int64_t> tiles;
  tiles.reserve(4 * n_drawn);
  const scalar_t amin = scalar_t(alpha_min);  // the compositor compares in scalar_t
  for (int64_t k = 0; k < n_drawn; ++k) {
    const int64_t g = drawn[k];
    const scalar_t mx = mean[2 * g], my = mean[2 * g + 1], rx = sup[2 * g], ry = sup[2 * g + 1];
    int64_t px0, py0, px1, py1;
    pixel_rect<scalar_t>(mx, my, rx, ry, width, height, px0, py0, px1, py1);
    const Ellipse e = cull ? ellipse_of<scalar_t>(con + 3 * g, opa[g], amin, mx, my) : Ellipse{0, 0, 0, 0, 0, 0, false};
    first[g] = static_cast<int64_t>(tiles.size());
    for (int64_t ty = py0 / ts; ty <= py1 / ts; ++ty)
      for (int64_t tx = px0 / ts; tx <= px1 / ts; ++tx)
        if (tile_reached(e, tx, ty, ts, px0, py0, px1, py1)) {
          tiles.push_back(ty * tiles_x + tx);
          off[ty * tiles_x + tx + 1] += 1;
        }
    count[g] = static_cast<int64_t>(tiles.size()) - first[g];
  }
  for (int64_t t = 0; t < n_tiles; ++t) off[t + 1] += off[t];
  const int64_t total = static_cast<int64_t>(tiles.size());
  b.pair_gauss = eg::empty_cpu({total}, at::kInt);
  b.pair_slot = eg::empty_cpu({total}, at::kLong);
  auto* pg = b.pair_gauss.data_ptr<int32_t>();
  auto* ps = b.pair_slot.data_ptr<int64_t>();
  std::vector<int64_t> cursor(off, off + n_tiles);
  for (int64_t k = 0; k < n_drawn; ++k) {  // front to back, so every tile's list is in depth order
    const int64_t g = drawn[k];
    for (int64_t slot = first[g]; slot < first[g] + count[g]; ++slot) {
      const int64_t j = cursor[tiles[slot]]++;
      pg[j] = static_cast<int32_t>(g);
      ps[j] = slot;
    }
  }
  return b;
}

// Constants of one compositing call.
template <typename scalar_t>
struct Model {
  int64_t width, height, ts, tiles_x, nf;  // nf = number of features (without the alpha channel)
  scalar_t alpha_max, alpha_min, t_min;
};

// One Gaussian's parameters, read once per (tile, Gaussian).
template <typename scalar_t>
struct Splat {
  scalar_t mx, my, a, b, c, o, rx, ry;
};

// Rows [y0, y1] of the tile (local indices) whose pixel centres lie inside the Gaussian's box
// (|dy| <= ry, exactly the per-pixel test); y0 > y1 when none.
template <typename scalar_t>
inline void row_range(const Splat<scalar_t>& s, scalar_t tile_y0, int64_t rows, int64_t& y0, int64_t& y1) {
  y0 = rows;
  y1 = -1;
  for (int64_t y = 0; y < rows; ++y) {
    const scalar_t dy = tile_y0 + scalar_t(y) + scalar_t(0.5) - s.my;
    if (std::abs(dy) <= s.ry) {
      y0 = std::min(y0, y);
      y1 = y;
    }
  }
}

// Vectors [c0, c1] of the row holding the columns whose pixel centres lie inside the box
// (|dx| <= rx, exactly the per-pixel test); c0 > c1 when none. The others are skipped: every
// lane there would add an exact zero.
template <typename scalar_t>
inline void vector_range(const scalar_t* dxs, scalar_t rx, int64_t cols, int64_t& c0, int64_t& c1) {
  constexpr int64_t L = Lanes<scalar_t>::N;
  int64_t x0 = cols, x1 = -1;
  for (int64_t x = 0; x < cols; ++x)
    if (std::abs(dxs[x]) <= rx) {
      x0 = std::min(x0, x);
      x1 = x;
    }
  c0 = x0 / L;
  c1 = x1 < 0 ? -1 : x1 / L;
}

template <typename scalar_t>
inline Splat<scalar_t> load_splat(int64_t g, const scalar_t* mean, const scalar_t* con, const scalar_t* opa,
                                  const scalar_t* sup) {
  return {mean[2 * g], mean[2 * g + 1], con[3 * g], con[3 * g + 1], con[3 * g + 2], opa[g], sup[2 * g], sup[2 * g + 1]};
}

// What the forward and the backward read once per (tile, Gaussian), so both walk exactly the same
// pixels: its features and a 1 in f, dx per column of the row in dxs, the rows [y0, y1] and the
// vectors [c0, c1] its box reaches.
template <typename scalar_t>
inline void enter_splat(const Splat<scalar_t>& s, const scalar_t* features, int64_t nf, int64_t px0, int64_t py0,
                        int64_t rows, int64_t cols, int64_t rs, scalar_t* f, scalar_t* dxs, int64_t& y0, int64_t& y1,
                        int64_t& c0, int64_t& c1) {
  for (int64_t k = 0; k < nf; ++k) f[k] = features[k];
  f[nf] = scalar_t(1);
  for (int64_t x = 0; x < rs; ++x) dxs[x] = scalar_t(px0) + scalar_t(x) + scalar_t(0.5) - s.mx;
  row_range(s, scalar_t(py0), rows, y0, y1);
  vector_range<scalar_t>(dxs, s.rx, cols, c0, c1);
}

// Features per Gaussian known at compile time (NF > 0: the rasterizer's colour + depth, NF = 4)
// let the compiler unroll the feature loops; NF = 0 reads md.nf.
template <int NF, typename scalar_t>
inline int64_t n_features(const Model<scalar_t>& md) {
  return NF > 0 ? NF : md.nf;
}

// A tile's pixel rows are stored with a stride of `rs` = tile width rounded up to whole vectors;
// the padding columns (and the columns past the image edge) start with live = 0, so they never
// take part.
template <typename scalar_t>
inline int64_t row_stride(int64_t ts) {
  constexpr int64_t n = Lanes<scalar_t>::N;
  return (ts + n - 1) / n * n;
}

// One Gaussian on one vector of pixels in a row: alpha, whether the pixel takes it (`used`) or
// stops before it (`stop`), given dx (pixel centre minus mean) and the row's terms of the power.
template <typename scalar_t>
struct PixelStep {
  using V = typename Lanes<scalar_t>::V;
  using M = typename Lanes<scalar_t>::M;
  V gauss, value, alpha, t_next;
  M used, stop;
  inline PixelStep(const Splat<scalar_t>& s, V dx, scalar_t cdy, scalar_t bdy, V T, V live, scalar_t amax,
                   scalar_t amin, scalar_t tmin) {
    const V power = scalar_t(-0.5) * (s.a * dx * dx + cdy) - bdy * dx;
    gauss = vexp(power);
    value = s.o * gauss;
    alpha = value < amax ? value : splat<V>(amax);
    const V adx = dx < scalar_t(0) ? -dx : dx;
    const M ok = (adx <= s.rx) & (alpha >= amin) & (live > scalar_t(0));
    t_next = T * (scalar_t(1) - alpha);
    stop = ok & (t_next < tmin);
    used = ok & ~stop;
  }
};

// Composites one tile. State per pixel p = y * rs + x: T[p] (transmittance), live[p] (1 until
// the stop), acc[k * np + p] (accumulated features, alpha last). A Gaussian is applied to the
// rows its box reaches, a vector of pixels at a time. With STATS, each pair's sums over the
// tile's pixels of w and of alpha, and the largest w, go to stats[3 * slot] (per-lane sums, then
// over the columns in order: a fixed order).
template <int NF, bool STATS, typename scalar_t>
void forward_tile(int64_t tile, const Model<scalar_t>& md, const int64_t* off, const int32_t* pg, const int64_t* ps,
                  const scalar_t* mean, const scalar_t* con, const scalar_t* opa, const scalar_t* sup,
                  const scalar_t* feat, scalar_t* out, scalar_t* stats, std::vector<scalar_t>& buf) {
  using V = typename Lanes<scalar_t>::V;
  using M = typename Lanes<scalar_t>::M;
  constexpr int64_t L = Lanes<scalar_t>::N;
  const int64_t nf = n_features<NF>(md), nf1 = nf + 1;
  const int64_t ts = md.ts, rs = row_stride<scalar_t>(ts), np = ts * rs;
  const int64_t px0 = (tile % md.tiles_x) * ts, py0 = (tile / md.tiles_x) * ts;
  const int64_t cols = std::min(ts, md.width - px0), rows = std::min(ts, md.height - py0);
  buf.assign(np * (2 + nf1) + rs + nf1, scalar_t(0));
  scalar_t* T = buf.data();
  scalar_t* live = T + np;
  scalar_t* acc = live + np;
  scalar_t* dxs = acc + nf1 * np;  // [rs] pixel centre minus mean, per column
  scalar_t* f = dxs + rs;          // [nf1] features of the current Gaussian and a 1
  int64_t n_live = 0;
  for (int64_t y = 0; y < rows; ++y)
    for (int64_t x = 0; x < cols; ++x) {
      T[y * rs + x] = scalar_t(1);
      live[y * rs + x] = scalar_t(1);
      ++n_live;
    }
  const scalar_t amax = md.alpha_max, amin = md.alpha_min, tmin = md.t_min;
  for (int64_t j = off[tile]; j < off[tile + 1] && n_live > 0; ++j) {
    const int64_t g = pg[j];
    const Splat<scalar_t> s = load_splat(g, mean, con, opa, sup);
    int64_t y0, y1, c0, c1;
    enter_splat(s, feat + g * nf, nf, px0, py0, rows, cols, rs, f, dxs, y0, y1, c0, c1);
    V w_sum[16], a_sum[16], w_max[16];  // per vector of columns (rs / L <= 16 for tiles up to 64 px wide)
    M n_stop = M{};
    for (int64_t c = 0; c < rs / L; ++c) w_sum[c] = a_sum[c] = w_max[c] = V{};
    for (int64_t y = y0; y <= y1; ++y) {
      const scalar_t dy = scalar_t(py0) + scalar_t(y) + scalar_t(0.5) - s.my;
      const scalar_t cdy = s.c * dy * dy, bdy = s.b * dy;
      for (int64_t c = c0; c <= c1; ++c) {  // vectors outside the box would add exact zeros
        const int64_t p = y * rs + c * L;
        const V Tv = load(T + p), lv = load(live + p);
        const PixelStep<scalar_t> st(s, load(dxs + c * L), cdy, bdy, Tv, lv, amax, amin, tmin);
        const V w = st.used ? st.alpha * Tv : V{};
        for (int64_t k = 0; k < nf1; ++k) store(acc + k * np + p, load(acc + k * np + p) + w * f[k]);
        store(T + p, st.used ? st.t_next : Tv);
        store(live + p, st.stop ? V{} : lv);
        n_stop -= st.stop;  // stop lanes are -1
        if (STATS) {
          w_sum[c] += w;
          a_sum[c] += st.used ? st.alpha : V{};
          w_max[c] = w > w_max[c] ? w : w_max[c];
        }
      }
    }
    for (int l = 0; l < L; ++l) n_live -= n_stop[l];
    if (STATS) {
      scalar_t ws = 0, as = 0, wm = 0;
      for (int64_t c = 0; c < rs / L; ++c)
        for (int l = 0; l < L; ++l) {
          ws += w_sum[c][l];
          as += a_sum[c][l];
          wm = std::max(wm, w_max[c][l]);
        }
      stats[3 * ps[j]] = ws;
      stats[3 * ps[j] + 1] = as;
      stats[3 * ps[j] + 2] = wm;
    }
  }
  for (int64_t y = 0; y < rows; ++y)
    for (int64_t x = 0; x < cols; ++x) {
      scalar_t* o = out + ((py0 + y) * md.width + px0 + x) * nf1;
      for (int64_t k = 0; k < nf1; ++k) o[k] = acc[k * np + y * rs + x];
    }
}

// The backward of one tile: the same front-to-back walk, writing each pair's gradient sums
// (mx, my, a, b, c, o, features) to pair_grad[slot * (6 + nf)]. Sums are kept per lane over the
// rows, then added over the columns in order. With ABS two more columns follow the features: the
// sums over the pixels of |dL/dmx| and |dL/dmy| of each pixel (AbsGS): a blurred Gaussian over
// texture, whose pixels pull its centre in opposite directions, has a small summed gradient but
// large absolute sums.
template <int NF, bool ABS, typename scalar_t>
void backward_tile(int64_t tile, const Model<scalar_t>& md, const int64_t* off, const int32_t* pg, const int64_t* ps,
                   const scalar_t* mean, const scalar_t* con, const scalar_t* opa, const scalar_t* sup,
                   const scalar_t* feat, const scalar_t* out, const scalar_t* gout, scalar_t* pair_grad,
                   std::vector<scalar_t>& buf) {
  using V = typename Lanes<scalar_t>::V;
  using M = typename Lanes<scalar_t>::M;
  constexpr int64_t L = Lanes<scalar_t>::N;
  constexpr int64_t MAXG = 6 + 16 + 2;  // gradient channels: 6 + up to 16 features + 2 absolute sums
  const int64_t nf = n_features<NF>(md), nf1 = nf + 1, ng = 6 + nf + (ABS ? 2 : 0);
  const int64_t ts = md.ts, rs = row_stride<scalar_t>(ts), np = ts * rs;
  const int64_t px0 = (tile % md.tiles_x) * ts, py0 = (tile / md.tiles_x) * ts;
  const int64_t cols = std::min(ts, md.width - px0), rows = std::min(ts, md.height - py0);
  // per pixel: T, live, prefix sum of w gf, total dL/dF . F, dL/dF (nf1 channels)
  buf.assign(np * (4 + nf1) + rs + nf1, scalar_t(0));
  scalar_t* T = buf.data();
  scalar_t* live = T + np;
  scalar_t* prefix = live + np;
  scalar_t* total = prefix + np;
  scalar_t* gpix = total + np;
  scalar_t* dxs = gpix + nf1 * np;
  scalar_t* f = dxs + rs;
  int64_t n_live = 0;
  for (int64_t y = 0; y < rows; ++y)
    for (int64_t x = 0; x < cols; ++x) {
      const int64_t p = y * rs + x;
      const int64_t pix = (py0 + y) * md.width + px0 + x;
      T[p] = scalar_t(1);
      live[p] = scalar_t(1);
      scalar_t dot = 0;
      for (int64_t k = 0; k < nf1; ++k) {
        gpix[k * np + p] = gout[pix * nf1 + k];
        dot += gout[pix * nf1 + k] * out[pix * nf1 + k];
      }
      total[p] = dot;
      ++n_live;
    }
  const scalar_t amax = md.alpha_max, amin = md.alpha_min, tmin = md.t_min;
  V sums[MAXG][16];  // [channel][vector of columns]
  for (int64_t j = off[tile]; j < off[tile + 1] && n_live > 0; ++j) {
    const int64_t g = pg[j];
    const Splat<scalar_t> s = load_splat(g, mean, con, opa, sup);
    int64_t y0, y1, c0, c1;
    enter_splat(s, feat + g * nf, nf, px0, py0, rows, cols, rs, f, dxs, y0, y1, c0, c1);
    for (int64_t q = 0; q < ng; ++q)
      for (int64_t c = 0; c < rs / L; ++c) sums[q][c] = V{};
    M n_stop = M{};
    for (int64_t y = y0; y <= y1; ++y) {
      const scalar_t dy = scalar_t(py0) + scalar_t(y) + scalar_t(0.5) - s.my;
      const scalar_t cdy = s.c * dy * dy, bdy = s.b * dy;
      for (int64_t c = c0; c <= c1; ++c) {  // vectors outside the box would add exact zeros
        const int64_t p = y * rs + c * L;
        const V dx = load(dxs + c * L);
        const V Tv = load(T + p), lv = load(live + p);
        const PixelStep<scalar_t> st(s, dx, cdy, bdy, Tv, lv, amax, amin, tmin);
        V gk[16 + 1];
        V gf = V{};
        for (int64_t k = 0; k < nf1; ++k) {
          gk[k] = load(gpix + k * np + p);
          gf += gk[k] * f[k];
        }
        const V w = st.used ? st.alpha * Tv : V{};
        const V pre = load(prefix + p) + w * gf;
        store(prefix + p, pre);
        const V behind = load(total + p) - pre;  // S_m: what the pairs behind this one add to dL/dF . F
        const V d_alpha = Tv * gf - behind / (scalar_t(1) - st.alpha);
        const M free = st.used & (st.value < amax);  // the clamp passes no gradient
        const V d_power = free ? st.alpha * d_alpha : V{};
        const V gmx = d_power * (s.a * dx + bdy), gmy = d_power * (s.b * dx + s.c * dy);
        sums[0][c] += gmx;
        sums[1][c] += gmy;
        if (ABS) {
          sums[6 + nf][c] += gmx < V{} ? -gmx : gmx;
          sums[7 + nf][c] += gmy < V{} ? -gmy : gmy;
        }
        sums[2][c] += scalar_t(-0.5) * d_power * dx * dx;
        sums[3][c] -= d_power * dx * dy;
        sums[4][c] += scalar_t(-0.5) * d_power * dy * dy;
        sums[5][c] += free ? st.gauss * d_alpha : V{};
        for (int64_t k = 0; k < nf; ++k) sums[6 + k][c] += w * gk[k];
        store(T + p, st.used ? st.t_next : Tv);
        store(live + p, st.stop ? V{} : lv);
        n_stop -= st.stop;
      }
    }
    for (int l = 0; l < L; ++l) n_live -= n_stop[l];
    scalar_t* dst = pair_grad + ps[j] * ng;
    for (int64_t q = 0; q < ng; ++q) {
      scalar_t sum = 0;
      for (int64_t c = 0; c < rs / L; ++c)
        for (int l = 0; l < L; ++l) sum += sums[q][c][l];
      dst[q] = sum;
    }
  }
}

// Tiles in order of decreasing pair count: the long ones start first, so the dynamic schedule
// ends with short tiles and the threads finish together.
std::vector<int64_t> tile_order(const int64_t* off, int64_t n_tiles) {
  std::vector<int64_t> order;
  order.reserve(n_tiles);
  for (int64_t t = 0; t < n_tiles; ++t)
    if (off[t + 1] > off[t]) order.push_back(t);
  std::stable_sort(order.begin(), order.end(),
                   [off](int64_t a, int64_t b) { return off[a + 1] - off[a] > off[b + 1] - off[b]; });
  return order;
}

template <typename scalar_t>
Model<scalar_t> make_model(int64_t width, int64_t height, int64_t ts, int64_t nf, double alpha_max, double alpha_min,
                           double t_min) {
  return {width, height, ts, (width + ts - 1) / ts, nf, scalar_t(alpha_max), scalar_t(alpha_min), scalar_t(t_min)};
}

// Largest tile side and feature count the kernels' fixed-size per-tile arrays hold.
constexpr int64_t MAX_TILE = 64, MAX_FEATURES = 16;

void check_inputs(const at::Tensor& means2d, const at::Tensor& conics, const at::Tensor& opacities,
                  const at::Tensor& feats, const at::Tensor& support, int64_t tile_size) {
  TORCH_CHECK(tile_size >= 1 && tile_size <= MAX_TILE, "composite_cpu: tile_size must be in 1..64");
  TORCH_CHECK(feats.size(1) <= MAX_FEATURES, "composite_cpu: at most 16 features per Gaussian");
  for (const auto* t : {&means2d, &conics, &opacities, &feats, &support}) {
    TORCH_CHECK(t->device().is_cpu(), "composite_cpu: tensors must be on the CPU");
    TORCH_CHECK(t->is_contiguous(), "composite_cpu: tensors must be contiguous");
    TORCH_CHECK(t->scalar_type() == means2d.scalar_type(), "composite_cpu: tensors must share one dtype");
  }
}


// Pointers of one compositing call's inputs.
template <typename scalar_t>
struct Inputs {
  const int64_t* off;
  const int32_t* pg;
  const int64_t* ps;
  const scalar_t *mean, *con, *opa, *sup, *feat;
};

template <typename scalar_t>
Inputs<scalar_t> inputs(const at::Tensor& tile_offsets, const at::Tensor& pair_gauss,
                        const at::Tensor& pair_slot, const at::Tensor& means2d, const at::Tensor& conics,
                        const at::Tensor& opacities, const at::Tensor& support, const at::Tensor& feats) {
  return {tile_offsets.data_ptr<int64_t>(), pair_gauss.data_ptr<int32_t>(), pair_slot.data_ptr<int64_t>(),
          means2d.data_ptr<scalar_t>(),     conics.data_ptr<scalar_t>(),    opacities.data_ptr<scalar_t>(),
          support.data_ptr<scalar_t>(),     feats.data_ptr<scalar_t>()};
}

template <typename scalar_t>
void forward_all(const Model<scalar_t>& md, const Inputs<scalar_t>& in, const std::vector<int64_t>& order,
                 bool stats, int64_t threads, scalar_t* out, scalar_t* pair_stats) {
  const int64_t n_work = static_cast<int64_t>(order.size());
#pragma omp parallel num_threads(std::max<int64_t>(1, std::min(threads, n_work)))
  {
    std::vector<scalar_t> buf;
#pragma omp for schedule(dynamic, 1)
    for (int64_t i = 0; i < n_work; ++i) {
      const int64_t t = order[i];
      if (md.nf == 4 && stats)
        forward_tile<4, true>(t, md, in.off, in.pg, in.ps, in.mean, in.con, in.opa, in.sup, in.feat, out, pair_stats, buf);
      else if (md.nf == 4)
        forward_tile<4, false>(t, md, in.off, in.pg, in.ps, in.mean, in.con, in.opa, in.sup, in.feat, out, pair_stats, buf);
      else if (stats)
        forward_tile<0, true>(t, md, in.off, in.pg, in.ps, in.mean, in.con, in.opa, in.sup, in.feat, out, pair_stats, buf);
      else
        forward_tile<0, false>(t, md, in.off, in.pg, in.ps, in.mean, in.con, in.opa, in.sup, in.feat, out, pair_stats, buf);
    }
  }
}

template <typename scalar_t>
void backward_all(const Model<scalar_t>& md, const Inputs<scalar_t>& in, const std::vector<int64_t>& order,
                  bool absolute, int64_t threads, const scalar_t* out, const scalar_t* gout, scalar_t* pair_grad) {
  const int64_t n_work = static_cast<int64_t>(order.size());
#pragma omp parallel num_threads(std::max<int64_t>(1, std::min(threads, n_work)))
  {
    std::vector<scalar_t> buf;
#pragma omp for schedule(dynamic, 1)
    for (int64_t i = 0; i < n_work; ++i) {
      const int64_t t = order[i];
      if (md.nf == 4 && absolute)
        backward_tile<4, true>(t, md, in.off, in.pg, in.ps, in.mean, in.con, in.opa, in.sup, in.feat, out, gout, pair_grad, buf);
      else if (md.nf == 4)
        backward_tile<4, false>(t, md, in.off, in.pg, in.ps, in.mean, in.con, in.opa, in.sup, in.feat, out, gout, pair_grad, buf);
      else if (absolute)
        backward_tile<0, true>(t, md, in.off, in.pg, in.ps, in.mean, in.con, in.opa, in.sup, in.feat, out, gout, pair_grad, buf);
      else
        backward_tile<0, false>(t, md, in.off, in.pg, in.ps, in.mean, in.con, in.opa, in.sup, in.feat, out, gout, pair_grad, buf);
    }
  }
}

// Columns k < c_sum are summed, the others take their largest value (from 0: they are >= 0).
template <typename scalar_t>
void sum_pairs_impl(const scalar_t* r, const int64_t* first, const int64_t* count, int64_t m, int64_t c,
                    int64_t c_sum, int64_t threads, scalar_t* dst) {
#pragma omp parallel for num_threads(std::max<int64_t>(1, threads)) schedule(static)
  for (int64_t g = 0; g < m; ++g)
    for (int64_t i = first[g]; i < first[g] + count[g]; ++i) {
      for (int64_t k = 0; k < c_sum; ++k) dst[g * c + k] += r[i * c + k];
      for (int64_t k = c_sum; k < c; ++k) dst[g * c + k] = std::max(dst[g * c + k], r[i * c + k]);
    }
}

}  // namespace

// Binning of the rows where `visible` [M] (bool) holds, front to back by `depths` [M] (ties by
// row; the other rows are not sorted), each with the tiles of its support box where, given its
// `conics` and `opacities`, its alpha may reach `alpha_min` (without them: every tile of the box):
// returns (tile_offsets [T+1], pair_gauss [P] int32,
// pair_slot [P], gauss_first [M], gauss_count [M], zero for a row not drawn). The rasterizer passes
// every projected row, so the compositor reads full-size tensors and no visible subset is gathered.
std::vector<at::Tensor> bin_tiles(at::Tensor means2d, at::Tensor support, at::Tensor depths, at::Tensor visible,
                                  std::optional<at::Tensor> conics, std::optional<at::Tensor> opacities,
                                  double alpha_min, int64_t width, int64_t height, int64_t tile_size) {
  TORCH_CHECK(means2d.is_contiguous() && support.is_contiguous() && depths.is_contiguous() && visible.is_contiguous(),
              "bin_tiles: contiguous");
  TORCH_CHECK(visible.scalar_type() == at::kBool && visible.numel() == means2d.size(0) &&
                  depths.numel() == means2d.size(0) && depths.scalar_type() == means2d.scalar_type(),
              "bin_tiles: one bool and one depth (of the means' dtype) per row");
  TORCH_CHECK(conics.has_value() == opacities.has_value(), "bin_tiles: conics and opacities together, or neither");
  at::Tensor con, opa;  // undefined: the whole box
  if (conics.has_value()) {
    con = *conics;
    opa = *opacities;
    TORCH_CHECK(con.is_contiguous() && opa.is_contiguous() && con.scalar_type() == means2d.scalar_type() &&
                    opa.scalar_type() == means2d.scalar_type() && con.numel() == 3 * means2d.size(0) &&
                    opa.numel() == means2d.size(0),
                "bin_tiles: contiguous conics [M, 3] and opacities [M] of the means' dtype");
    TORCH_CHECK(alpha_min > 0.0, "bin_tiles: alpha_min > 0");
  }
  Bins b;
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "bin_tiles", [&] {
    b = bin_impl<scalar_t>(means2d, support, depths, visible, con, opa, alpha_min, width, height, tile_size);
  });
  return {b.tile_offsets, b.pair_gauss, b.pair_slot, b.gauss_first, b.gauss_count};
}

// Forward: out [H, W, F+1] (features, then alpha) and, with stats, per-pair [P, 3]: the sums of w
// and of alpha over the tile's pixels, and the largest w.
std::vector<at::Tensor> composite_forward(at::Tensor means2d, at::Tensor conics, at::Tensor opacities,
                                             at::Tensor feats, at::Tensor support, at::Tensor tile_offsets,
                                             at::Tensor pair_gauss, at::Tensor pair_slot, int64_t width,
                                             int64_t height, int64_t tile_size, double alpha_max, double alpha_min,
                                             double t_min, bool stats, int64_t threads) {
  check_inputs(means2d, conics, opacities, feats, support, tile_size);
  const int64_t nf = feats.size(1), n_tiles = tile_offsets.size(0) - 1, n_pairs = pair_gauss.size(0);
  auto out = eg::zeros_cpu({height, width, nf + 1}, means2d.scalar_type());
  auto pair_stats = eg::zeros_cpu({stats ? n_pairs : 0, 3}, means2d.scalar_type());
  const auto order = tile_order(tile_offsets.data_ptr<int64_t>(), n_tiles);
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "composite_forward", [&] {
    const auto md = make_model<scalar_t>(width, height, tile_size, nf, alpha_max, alpha_min, t_min);
    const auto in = inputs<scalar_t>(tile_offsets, pair_gauss, pair_slot, means2d, conics, opacities, support, feats);
    forward_all<scalar_t>(md, in, order, stats, threads, out.data_ptr<scalar_t>(), pair_stats.data_ptr<scalar_t>());
  });
  return {out, pair_stats};
}

// Backward: per-pair gradient sums [P, 6 + F] in making order (mx, my, a, b, c, o, features).
at::Tensor composite_backward(at::Tensor means2d, at::Tensor conics, at::Tensor opacities,
                                 at::Tensor feats, at::Tensor support, at::Tensor tile_offsets,
                                 at::Tensor pair_gauss, at::Tensor pair_slot, at::Tensor out,
                                 at::Tensor grad_out, int64_t width, int64_t height, int64_t tile_size,
                                 double alpha_max, double alpha_min, double t_min, bool absolute,
                                 int64_t threads) {
  check_inputs(means2d, conics, opacities, feats, support, tile_size);
  TORCH_CHECK(out.is_contiguous() && grad_out.is_contiguous(), "composite_backward: contiguous");
  const int64_t nf = feats.size(1), n_tiles = tile_offsets.size(0) - 1, n_pairs = pair_gauss.size(0);
  auto pair_grad = eg::zeros_cpu({n_pairs, 6 + nf + (absolute ? 2 : 0)}, means2d.scalar_type());
  const auto order = tile_order(tile_offsets.data_ptr<int64_t>(), n_tiles);
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "composite_backward", [&] {
    const auto md = make_model<scalar_t>(width, height, tile_size, nf, alpha_max, alpha_min, t_min);
    const auto in = inputs<scalar_t>(tile_offsets, pair_gauss, pair_slot, means2d, conics, opacities, support, feats);
    backward_all<scalar_t>(md, in, order, absolute, threads, out.data_ptr<scalar_t>(), grad_out.data_ptr<scalar_t>(),
                           pair_grad.data_ptr<scalar_t>());
  });
  return pair_grad;
}

// Per-Gaussian sums of per-pair rows [P, C] (making order): out[g] = sum of rows first[g] ..
// first[g] + count[g] - 1, in that order (a fixed order: the same bits at any thread count); the
// last C - c_sum columns take the largest value instead (a peak, from 0).
at::Tensor sum_pairs(at::Tensor rows, at::Tensor gauss_first, at::Tensor gauss_count, int64_t c_sum,
                     int64_t threads) {
  TORCH_CHECK(rows.is_contiguous(), "sum_pairs: contiguous");
  const int64_t m = gauss_first.size(0), c = rows.size(1);
  TORCH_CHECK(c_sum >= 0 && c_sum <= c, "sum_pairs: c_sum in [0, C]");
  auto res = eg::zeros_cpu({m, c}, rows.scalar_type());
  const auto* first = gauss_first.data_ptr<int64_t>();
  const auto* count = gauss_count.data_ptr<int64_t>();
  AT_DISPATCH_FLOATING_TYPES(rows.scalar_type(), "sum_pairs", [&] {
    sum_pairs_impl<scalar_t>(rows.data_ptr<scalar_t>(), first, count, m, c, c_sum, threads, res.data_ptr<scalar_t>());
  });
  return res;
}
