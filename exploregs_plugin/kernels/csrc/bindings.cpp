// The Python module of the compiled CPU kernels: one table of the functions the other units define.
// The binding alone needs pybind11 and torch's tensor casters (torch/csrc/utils/pybind.h), not the
// whole of torch/extension.h, which every unit compiled in before and which cost about five times
// the CPU time (docs/training.md, "Building the kernels").

#include <ATen/core/Tensor.h>
#include <torch/csrc/utils/pybind.h>

#include <cstdint>
#include <optional>
#include <vector>

// composite_cpu.cpp
std::vector<at::Tensor> bin_tiles(at::Tensor means2d, at::Tensor support, at::Tensor depths, at::Tensor visible,
                                  std::optional<at::Tensor> conics, std::optional<at::Tensor> opacities,
                                  double alpha_min, int64_t width, int64_t height, int64_t tile_size);
std::vector<at::Tensor> composite_forward(at::Tensor means2d, at::Tensor conics, at::Tensor opacities,
                                          at::Tensor feats, at::Tensor support, at::Tensor tile_offsets,
                                          at::Tensor pair_gauss, at::Tensor pair_slot, int64_t width,
                                          int64_t height, int64_t tile_size, double alpha_max, double alpha_min,
                                          double t_min, bool stats, int64_t threads);
at::Tensor composite_backward(at::Tensor means2d, at::Tensor conics, at::Tensor opacities, at::Tensor feats,
                              at::Tensor support, at::Tensor tile_offsets, at::Tensor pair_gauss,
                              at::Tensor pair_slot, at::Tensor out, at::Tensor grad_out, int64_t width,
                              int64_t height, int64_t tile_size, double alpha_max, double alpha_min, double t_min,
                              bool absolute, int64_t threads);
at::Tensor sum_pairs(at::Tensor rows, at::Tensor gauss_first, at::Tensor gauss_count, int64_t c_sum,
                     int64_t threads);

// project_cpu.cpp
std::vector<at::Tensor> project_forward(at::Tensor means, at::Tensor quats, at::Tensor scales,
                                           at::Tensor opacities, at::Tensor viewmat, at::Tensor K,
                                           int64_t width, int64_t height, double near, double far, double eps2d,
                                           double sigma_radius, double guard_band, bool antialiased, double alpha_min,
                                           int64_t threads);
std::vector<at::Tensor> project_backward(at::Tensor means, at::Tensor quats, at::Tensor scales,
                                            at::Tensor opacities, at::Tensor viewmat, at::Tensor K,
                                            int64_t width, int64_t height, double near, double far, double eps2d,
                                            double sigma_radius, double guard_band, bool antialiased,
                                            at::Tensor g_means2d, at::Tensor g_conics, at::Tensor g_opac,
                                            at::Tensor g_depths, int64_t threads);

// sh_cpu.cpp
at::Tensor sh_forward(at::Tensor sh0, at::Tensor shN, at::Tensor means, at::Tensor visible, at::Tensor camera,
                         int64_t degree, int64_t threads);
std::vector<at::Tensor> sh_backward(at::Tensor sh0, at::Tensor shN, at::Tensor means, at::Tensor visible,
                                       at::Tensor camera, int64_t degree, at::Tensor g_colors, int64_t threads);

// photometric_cpu.cpp
std::vector<at::Tensor> photometric_forward(at::Tensor img, at::Tensor ref, double lambda, double c1, double c2,
                                            double mse_floor, int64_t threads);
at::Tensor photometric_backward(at::Tensor moments, at::Tensor grad_loss, double lambda, double c1, double c2,
                                int64_t threads);

// rows_cpu.cpp
std::vector<at::Tensor> gather_rows(std::vector<at::Tensor> tensors, at::Tensor order, std::vector<int64_t> zero_from);

// watch_cpu.cpp
void watch_params_(std::vector<at::Tensor> tensors, std::vector<int64_t> by_row, at::Tensor record, int64_t step,
                   int64_t num_gaussians, int64_t threads);
void watch_loss_(std::vector<at::Tensor> values, at::Tensor record, int64_t step);

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("photometric_forward", &photometric_forward, "(1 - lambda) L1 + lambda (1 - SSIM) (forward)");
  m.def("photometric_backward", &photometric_backward, "(1 - lambda) L1 + lambda (1 - SSIM) (backward)");
  m.def("sh_forward", &sh_forward, "SH colours (forward)");
  m.def("sh_backward", &sh_backward, "SH colours (backward)");
  m.def("project_forward", &project_forward, "EWA projection (forward)");
  m.def("project_backward", &project_backward, "EWA projection (backward)");
  m.def("bin_tiles", &bin_tiles, "Tile-Gaussian pairs, front to back per tile");
  m.def("composite_forward", &composite_forward, "Front-to-back compositing (forward)");
  m.def("composite_backward", &composite_backward, "Front-to-back compositing (backward, per-pair sums)");
  m.def("watch_params_", &watch_params_, "The first step with non-finite parameters, recorded in place");
  m.def("watch_loss_", &watch_loss_, "The first step with a non-finite loss, recorded in place");
  m.def("gather_rows", &gather_rows, "Rows of many tensors in a new order, in one call");
  m.def("sum_pairs", &sum_pairs, "Per-Gaussian sums (and peaks) of per-pair rows in a fixed order");
}
