// The non-finite watch of a training step on the CPU: how many rows of each trained tensor hold a
// NaN or an inf, for all of them in one call (exploregs_plugin/engine/nonfinite.py). In torch it
// was five operators a tensor (a product by 0, its row sums, isfinite, a sum and a subtraction),
// about thirty a step, each a pass over the tensor or its rows.
//
// A float is non-finite exactly when its exponent bits are all ones (inf: mantissa 0, NaN: not),
// so the test is an integer mask and compare on the value's bits, which vectorises (an OR over a
// row, a sum of integers over rows), cannot overflow, and is exact: the same counts at any thread
// count.

#include <ATen/Dispatch.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>

#include <omp.h>

#include <algorithm>
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

// tensors: the trained tensors; by_row[k]: count tensor k's rows along dim 0 (a Gaussian
// parameter), else its values (a model part's). Returns [K] int64 on the CPU.
at::Tensor nonfinite_counts(std::vector<at::Tensor> tensors, std::vector<int64_t> by_row, int64_t threads) {
  TORCH_CHECK(tensors.size() == by_row.size(), "nonfinite_counts: one by_row flag per tensor");
  auto counts = at::empty({int64_t(tensors.size())}, at::TensorOptions().dtype(at::kLong));
  int64_t* out = counts.data_ptr<int64_t>();
  for (size_t k = 0; k < tensors.size(); ++k) {
    at::Tensor t = tensors[k].is_contiguous() ? tensors[k] : tensors[k].contiguous();
    TORCH_CHECK(t.device().is_cpu(), "nonfinite_counts: CPU tensors only");
    const int64_t n = t.numel();
    const bool rows = by_row[k] && t.dim() > 1 && t.size(0) > 0;
    const int64_t count = rows ? t.size(0) : n, width = rows ? n / t.size(0) : 1;
    AT_DISPATCH_FLOATING_TYPES(t.scalar_type(), "nonfinite_counts", [&] {
      out[k] = n == 0 ? 0 : nonfinite_rows<scalar_t>(t.data_ptr<scalar_t>(), count, width, threads);
    });
  }
  return counts;
}
