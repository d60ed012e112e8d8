// Tensors the kernels make, and small ones they read, without a trip through the dispatcher.
// Each at::empty, at::zeros or .to() a kernel called was one more operator of a training step (a
// dispatch and a profiler event: docs/training.md, "Operators per step") for an allocation or a
// 4 x 4 camera matrix.

#pragma once

#include <ATen/Dispatch.h>
#include <ATen/EmptyTensor.h>
#include <ATen/core/Tensor.h>

#include <cstdint>
#include <cstring>

namespace eg {

// A contiguous CPU tensor of `sizes`, uninitialised.
inline at::Tensor empty_cpu(at::IntArrayRef sizes, at::ScalarType dtype) {
  return at::Tensor(at::detail::empty_cpu(sizes, dtype));
}

// A contiguous CPU tensor of `sizes` filled with zeros (all bits zero: +0 in every float dtype).
inline at::Tensor zeros_cpu(at::IntArrayRef sizes, at::ScalarType dtype) {
  at::Tensor t = empty_cpu(sizes, dtype);
  if (t.nbytes() > 0) std::memset(t.data_ptr(), 0, t.nbytes());
  return t;
}

// The first `n` values of a small floating-point CPU tensor in row-major order, as doubles (a
// float32 value converts exactly).
inline void read_doubles(const at::Tensor& t, double* out, int64_t n) {
  const at::Tensor c = t.is_contiguous() ? t : t.contiguous();
  TORCH_CHECK(c.numel() >= n, "read_doubles: too few values");
  AT_DISPATCH_FLOATING_TYPES(c.scalar_type(), "read_doubles", [&] {
    const scalar_t* v = c.data_ptr<scalar_t>();
    for (int64_t i = 0; i < n; ++i) out[i] = double(v[i]);
  });
}

// `t` with unit stride inside a row (its rows may lie apart, as the columns of one gradient block
// do): a copy only where a row itself is strided.
inline at::Tensor rows_of(const at::Tensor& t) {
  return t.dim() < 2 || t.stride(1) == 1 ? t : t.contiguous();
}

}  // namespace eg
