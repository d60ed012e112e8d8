// The rows of many tensors in a new order, in one call: a densification's new set on the CPU
// (exploregs_plugin/strategies/row_ops.py: a split puts the kept rows first, then each parent
// twice). In torch that was a gather per parameter and per Adam moment, and a slice per moment for
// the children's zero moments: about thirty operators at every step of Seed+Split's growth.
// A row is copied as bytes, so the values are those of index_select, bit for bit, in any dtype.

#include "tensors.h"
#include <ATen/core/Tensor.h>

#include <cstdint>
#include <cstring>
#include <vector>

// out[k] = tensors[k][order] along dim 0; rows [zero_from[k], len(order)) of out[k] set to zero
// where zero_from[k] >= 0. Every tensor: a contiguous CPU tensor of at least one dimension.
std::vector<at::Tensor> gather_rows(std::vector<at::Tensor> tensors, at::Tensor order, std::vector<int64_t> zero_from) {
  TORCH_CHECK(order.device().is_cpu() && order.scalar_type() == at::kLong && order.dim() == 1 && order.is_contiguous(),
              "gather_rows: order must be a contiguous CPU int64 vector");
  TORCH_CHECK(zero_from.size() == tensors.size(), "gather_rows: one zero_from entry per tensor");
  const int64_t m = order.numel();
  const int64_t* idx = order.data_ptr<int64_t>();
  std::vector<at::Tensor> out;
  out.reserve(tensors.size());
  for (size_t k = 0; k < tensors.size(); ++k) {
    const at::Tensor& t = tensors[k];
    TORCH_CHECK(t.device().is_cpu() && t.is_contiguous() && t.dim() >= 1, "gather_rows: contiguous CPU tensors");
    const int64_t n = t.size(0);
    std::vector<int64_t> sizes = t.sizes().vec();
    sizes[0] = m;
    at::Tensor o = eg::empty_cpu(sizes, t.scalar_type());
    const int64_t row_bytes = m > 0 ? int64_t(o.nbytes()) / m : 0;
    const char* src = static_cast<const char*>(t.data_ptr());
    char* dst = static_cast<char*>(o.data_ptr());
    for (int64_t i = 0; i < m; ++i) {
      TORCH_CHECK(idx[i] >= 0 && idx[i] < n, "gather_rows: index ", idx[i], " out of range for ", n, " rows");
      std::memcpy(dst + i * row_bytes, src + idx[i] * row_bytes, size_t(row_bytes));
    }
    const int64_t z = zero_from[k];
    if (z >= 0 && z < m) std::memset(dst + z * row_bytes, 0, size_t((m - z) * row_bytes));
    out.push_back(o);
  }
  return out;
}
