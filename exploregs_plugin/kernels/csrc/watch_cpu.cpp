// The non-finite watch of a training step on the CPU (exploregs_plugin/engine/nonfinite.py): the
// first step whose loss went non-finite, and the first whose parameters did with how many rows of
// each trained tensor hold a NaN or an inf, each recorded in place by one call. In torch the counts
// were five operators a tensor (a product by 0, its row sums, isfinite, a sum and a subtraction),
// each a pass over the tensor or its rows, and each record a test and a `where` per value.
//
// A float is non-finite exactly when its exponent bits are all ones (inf: mantissa 0, NaN: not),
// so the test is an integer mask and compare on the value's bits, which vectorises (an OR over a
// row, a sum of integers over rows), cannot overflow, and is exact: the same counts at any thread
// count.

#include <ATen/Dispatch.h>
#include <ATen/core/Tensor.h>

#include <omp.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <type_traits>
#include <vector>

namespace {

template <typename scalar_t>
struct Bits;
template <>
struct Bits<float> {
  using type = uint32_t;
  static constexpr uint32_t exponent = 0x7f800000u;
};
template <>
struct Bits<double> {
  using type = uint64_t;
  static constexpr uint64_t exponent = 0x7ff0000000000000ull;
};

// Rows of [rows, width] values that hold at least one non-finite value.
template <typename scalar_t>
int64_t nonfinite_rows(const scalar_t* values, int64_t rows, int64_t width, int64_t threads) {
  using bits_t = typename Bits<scalar_t>::type;
  constexpr bits_t mask = Bits<scalar_t>::exponent;
  int64_t bad = 0;
#pragma omp parallel for reduction(+ : bad) schedule(static) num_threads(std::max<int64_t>(1, threads))
  for (int64_t r = 0; r < rows; ++r) {
    const scalar_t* row = values + r * width;
    bits_t any = 0;
    for (int64_t j = 0; j < width; ++j) {
      bits_t b;
      std::memcpy(&b, row + j, sizeof(b));
      any |= bits_t((b & mask) == mask);
    }
    bad += any != 0;
  }
  return bad;
}

}  // namespace

namespace {

// counts[k]: tensor k's rows (by_row[k], a Gaussian parameter) or values (a model part's) that
// hold a NaN or an inf.
void count_into(const std::vector<at::Tensor>& tensors, const std::vector<int64_t>& by_row, int64_t* counts,
                int64_t threads) {
  TORCH_CHECK(tensors.size() == by_row.size(), "watch_params_: one by_row flag per tensor");
  for (size_t k = 0; k < tensors.size(); ++k) {
    at::Tensor t = tensors[k].is_contiguous() ? tensors[k] : tensors[k].contiguous();
    TORCH_CHECK(t.device().is_cpu(), "watch_params_: CPU tensors only");
    const int64_t n = t.numel();
    const bool rows = by_row[k] && t.dim() > 1 && t.size(0) > 0;
    const int64_t count = rows ? t.size(0) : n, width = rows ? n / t.size(0) : 1;
    AT_DISPATCH_FLOATING_TYPES(t.scalar_type(), "watch_params_", [&] {
      counts[k] = n == 0 ? 0 : nonfinite_rows<scalar_t>(t.data_ptr<scalar_t>(), count, width, threads);
    });
  }
}

}  // namespace

// The parameters' record of a step, in place (one operator instead of a count and six more):
// record = [the first step with a non-finite parameter (-1 until one), the Gaussian count at that
// step, each tensor's count at that step]. Once a step is recorded nothing is counted again.
void watch_params_(std::vector<at::Tensor> tensors, std::vector<int64_t> by_row, at::Tensor record, int64_t step,
                   int64_t num_gaussians, int64_t threads) {
  TORCH_CHECK(record.device().is_cpu() && record.scalar_type() == at::kLong && record.is_contiguous() &&
                  record.numel() == int64_t(tensors.size()) + 2,
              "watch_params_: record must be a contiguous CPU int64 tensor of 2 + K values");
  int64_t* r = record.data_ptr<int64_t>();
  if (r[0] >= 0) return;
  std::vector<int64_t> counts(tensors.size());
  count_into(tensors, by_row, counts.data(), threads);
  if (std::all_of(counts.begin(), counts.end(), [](int64_t c) { return c == 0; })) return;
  r[0] = step;
  r[1] = num_gaussians;
  std::copy(counts.begin(), counts.end(), r + 2);
}

// The loss's record of a step, in place (one operator instead of a where per value and three
// more): record = [the first step whose loss (values[0]) is non-finite (-1 until one), then that
// step's values]. values: 0-dim float64 CPU tensors (the loss, the PSNR and the terms).
void watch_loss_(std::vector<at::Tensor> values, at::Tensor record, int64_t step) {
  TORCH_CHECK(record.device().is_cpu() && record.scalar_type() == at::kDouble && record.is_contiguous() &&
                  record.numel() == int64_t(values.size()) + 1 && !values.empty(),
              "watch_loss_: record must be a contiguous CPU float64 tensor of 1 + K values");
  double* r = record.data_ptr<double>();
  for (const at::Tensor& v : values)
    TORCH_CHECK(v.device().is_cpu() && v.scalar_type() == at::kDouble && v.numel() == 1,
                "watch_loss_: each value must be one CPU float64");
  if (r[0] >= 0.0 || std::isfinite(*values[0].data_ptr<double>())) return;
  r[0] = double(step);
  for (size_t k = 0; k < values.size(); ++k) r[k + 1] = *values[k].data_ptr<double>();
}
