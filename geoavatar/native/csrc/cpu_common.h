// What GeoAvatar's native CPU extensions share (render/csrc/rasterize_cpu.cpp, avatar/csrc/binding_cpu.cpp,
// imaging/csrc/ssim_cpu.cpp):
// the torch headers they need, their thread count, a parallel loop and the input checks. geoavatar/native
// copies this header beside each extension's source in its build folder, so `#include "cpu_common.h"` finds it.
//
// The headers are ATen's, torch's Tensor aliases and torch's pybind11 casters, not <torch/extension.h>: that one
// also pulls in the whole C++ frontend (nn, optim, data), about 10 s more of compiling per extension on our
// machines, for nothing these kernels use.
#pragma once

#include <ATen/Parallel.h>
#include <omp.h>
#include <torch/csrc/utils/pybind.h>
#include <torch/types.h>

#include <algorithm>
#include <cstdint>

namespace geoavatar_native {

// The threads torch uses (torch.set_num_threads / --threads): the OpenMP loops use as many.
inline int threads_for_torch() { return std::max(1, at::get_num_threads()); }

// OpenMP pragmas cannot sit inside AT_DISPATCH's macro argument: loops over elements go through this.
template <typename Body>
void parallel_over(int64_t n, const Body& body) {
#pragma omp parallel for schedule(static) num_threads(threads_for_torch())
  for (int64_t i = 0; i < n; ++i) body(i);
}

// A kernel's tensor argument: on the CPU, contiguous, `dim` dimensions, of `dtype`.
inline void check_input(const torch::Tensor& t, const char* name, int64_t dim, torch::ScalarType dtype) {
  TORCH_CHECK(t.device().is_cpu(), "native kernel: '", name, "' must be a CPU tensor");
  TORCH_CHECK(t.is_contiguous(), "native kernel: '", name, "' must be contiguous");
  TORCH_CHECK(t.dim() == dim, "native kernel: '", name, "' must have ", dim, " dimensions");
  TORCH_CHECK(t.scalar_type() == dtype, "native kernel: '", name, "' has dtype ", t.scalar_type(), ", expected ",
              dtype);
}

// The GIL is released while a kernel runs (arguments and results are tensors, converted outside the guard):
// other Python threads (drive's fit beside its render, a viewer) keep running meanwhile.
using release_gil = pybind11::call_guard<pybind11::gil_scoped_release>;

}  // namespace geoavatar_native
