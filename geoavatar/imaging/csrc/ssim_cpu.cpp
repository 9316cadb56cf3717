// 3DGS's SSIM of channel-last images, fused (imaging/quality.py's ssim): the five Gaussian-blurred moments of each
// channel, the mean of the SSIM map and its gradient with respect to the first image, in a few passes over planar
// copies instead of ten convolutions and some thirty image-sized PyTorch ops forward and as many backward.
//
// Forward, per channel plane: x, y, x^2, y^2, xy blurred by the separable window with zero padding (3DGS's
// padding of window // 2); per pixel mu_x, mu_y, s_x = E[x^2] - mu_x^2, s_y, s_xy = E[xy] - mu_x mu_y and
//   S = A1 A2 / (B1 B2),  A1 = 2 mu_x mu_y + C1, A2 = 2 s_xy + C2, B1 = mu_x^2 + mu_y^2 + C1, B2 = s_x + s_y + C2.
// With the gradient asked for it keeps dS/dmu_x, dS/dE[x^2], dS/dE[xy] per pixel (mu_y and E[y^2] do not depend on
// x):
//   dS/dmu_x = (2 mu_y (A2 - A1) - 2 mu_x S (B2 - B1)) / (B1 B2),  dS/dE[x^2] = -S / B2,  dS/dE[xy] = 2 A1 / (B1 B2).
// Backward: a zero-padded blur with a symmetric window is its own transpose, so the three maps are blurred once
// more and dL/dx = g / count * (blur(dS/dmu_x) + 2 x blur(dS/dE[x^2]) + y blur(dS/dE[xy])).
#include "cpu_common.h"

#include <vector>

namespace {

using geoavatar_native::check_input;
using geoavatar_native::parallel_over;

// out[i] += w * in[i] over a row: the blur's inner loop, also compiled for AVX2 and picked at run time (the
// build has no -march: the same cache serves any x86-64 machine). No FMA: the same sums on every path.
#if defined(__x86_64__) && defined(__GNUC__)
__attribute__((target_clones("avx2", "default")))
#endif
void add_scaled(float* __restrict out, const float* __restrict in, float w, int64_t n) {
  for (int64_t i = 0; i < n; ++i) out[i] += w * in[i];
}

void add_scaled(double* __restrict out, const double* __restrict in, double w, int64_t n) {
  for (int64_t i = 0; i < n; ++i) out[i] += w * in[i];
}

// Zero-padded separable blur of `planes` planes [P][H][W] in place, window w [K] (K odd, symmetric: the backward
// uses the blur as its own transpose); tmp: as large.
// Each pass adds whole shifted rows (contiguous, so the compiler vectorises the inner loop).
template <typename T>
void blur_planes(T* data, T* tmp, int64_t planes, int64_t H, int64_t W, const T* w, int64_t K) {
  const int64_t r = K / 2;
  parallel_over(planes * H, [&](int64_t row) {  // along x: data -> tmp
    const T* in = data + row * W;
    T* out = tmp + row * W;
    std::fill(out, out + W, T(0));
    for (int64_t k = 0; k < K; ++k) {
      const int64_t shift = k - r;
      const T wk = w[k];
      const int64_t lo = std::max<int64_t>(0, -shift), hi = std::min<int64_t>(W, W - shift);
      if (hi > lo) add_scaled(out + lo, in + lo + shift, wk, hi - lo);  // a row narrower than the window
    }
  });
  parallel_over(planes * H, [&](int64_t row) {  // along y: tmp -> data
    const int64_t plane = row / H, y = row % H;
    T* out = data + row * W;
    std::fill(out, out + W, T(0));
    for (int64_t i = std::max<int64_t>(0, y - r); i <= std::min<int64_t>(H - 1, y + r); ++i) {
      add_scaled(out, tmp + (plane * H + i) * W, w[i - y + r], W);
    }
  });
}

struct Shape {
  int64_t images, H, W, C;
  int64_t plane() const { return H * W; }
  int64_t planes() const { return images * C; }
  int64_t count() const { return images * H * W * C; }
};

Shape shape_of(const torch::Tensor& x) {
  return {x.size(0), x.size(1), x.size(2), x.size(3)};
}

// Planar moments [5][P][H][W]: x, y, x^2, y^2, xy of each channel plane p = image * C + channel.
template <typename T>
void fill_moments(const T* x, const T* y, T* m, const Shape& s) {
  const int64_t P = s.planes(), HW = s.plane();
  parallel_over(P, [&](int64_t p) {
    const int64_t image = p / s.C, c = p % s.C;
    const T* xs = x + image * HW * s.C + c;
    const T* ys = y + image * HW * s.C + c;
    T* out = m + p * HW;
    for (int64_t i = 0; i < HW; ++i) {
      const T xv = xs[i * s.C], yv = ys[i * s.C];
      out[i] = xv;
      out[P * HW + i] = yv;
      out[2 * P * HW + i] = xv * xv;
      out[3 * P * HW + i] = yv * yv;
      out[4 * P * HW + i] = xv * yv;
    }
  });
}

template <typename T>
std::vector<torch::Tensor> forward_impl(const torch::Tensor& image, const torch::Tensor& target,
                                        const torch::Tensor& window, bool need_grad) {
  const Shape s = shape_of(image);
  const int64_t P = s.planes(), HW = s.plane(), n = P * HW;
  auto moments = torch::empty({5, P, s.H, s.W}, image.options());
  auto tmp = torch::empty_like(moments);
  T* m = moments.data_ptr<T>();
  fill_moments(image.data_ptr<T>(), target.data_ptr<T>(), m, s);
  blur_planes(m, tmp.data_ptr<T>(), 5 * P, s.H, s.W, window.data_ptr<T>(), window.size(0));
  auto coefficients = need_grad ? torch::empty({3, P, s.H, s.W}, image.options()) : torch::empty({0}, image.options());
  T* g = need_grad ? coefficients.data_ptr<T>() : nullptr;
  const T c1 = T(0.01 * 0.01), c2 = T(0.03 * 0.03);
  const int64_t blocks = std::max<int64_t>(1, std::min<int64_t>(n, 256));
  std::vector<double> partial(blocks, 0.0);
  parallel_over(blocks, [&](int64_t b) {
    double sum = 0.0;
    for (int64_t i = n * b / blocks; i < n * (b + 1) / blocks; ++i) {
      const T mx = m[i], my = m[n + i];
      const T sx = m[2 * n + i] - mx * mx, sy = m[3 * n + i] - my * my, sxy = m[4 * n + i] - mx * my;
      const T a1 = 2 * mx * my + c1, a2 = 2 * sxy + c2, b1 = mx * mx + my * my + c1, b2 = sx + sy + c2;
      const T d = b1 * b2, value = a1 * a2 / d;
      sum += value;
      if (g != nullptr) {
        g[i] = (2 * my * (a2 - a1) - 2 * mx * value * (b2 - b1)) / d;
        g[n + i] = -value / b2;
        g[2 * n + i] = 2 * a1 / d;
      }
    }
    partial[b] = sum;
  });
  double total = 0.0;
  for (double v : partial) total += v;
  return {torch::full({}, total / double(s.count()), image.options()), coefficients};
}

template <typename T>
torch::Tensor backward_impl(double grad, const torch::Tensor& image, const torch::Tensor& target,
                            const torch::Tensor& window, const torch::Tensor& coefficients) {
  const Shape s = shape_of(image);
  const int64_t P = s.planes(), HW = s.plane(), n = P * HW;
  auto blurred = coefficients.clone();
  auto tmp = torch::empty_like(blurred);
  T* b = blurred.data_ptr<T>();
  blur_planes(b, tmp.data_ptr<T>(), 3 * P, s.H, s.W, window.data_ptr<T>(), window.size(0));
  auto out = torch::empty_like(image);
  const T* x = image.data_ptr<T>();
  const T* y = target.data_ptr<T>();
  T* dx = out.data_ptr<T>();
  const T scale = T(grad / double(s.count()));
  parallel_over(P, [&](int64_t p) {
    const int64_t image_index = p / s.C, c = p % s.C;
    const int64_t base = image_index * HW * s.C + c;
    for (int64_t i = 0; i < HW; ++i) {
      const int64_t at = base + i * s.C, k = p * HW + i;
      dx[at] = scale * (b[k] + 2 * x[at] * b[n + k] + y[at] * b[2 * n + k]);
    }
  });
  return out;
}

void check_images(const torch::Tensor& image, const torch::Tensor& target, const torch::Tensor& window) {
  check_input(image, "image", 4, image.scalar_type());
  check_input(target, "target", 4, image.scalar_type());
  check_input(window, "window", 1, image.scalar_type());
  TORCH_CHECK(image.sizes() == target.sizes(), "ssim: image and target differ in shape");
  TORCH_CHECK(window.size(0) % 2 == 1, "ssim: the window must have an odd size");
  TORCH_CHECK(image.scalar_type() == torch::kFloat || image.scalar_type() == torch::kDouble,
              "ssim: float32 or float64 images");
}

// (mean SSIM [], dS/d(mu_x, E[x^2], E[xy]) [3, N*C, H, W] or [0]) of [N, H, W, C] images.
std::vector<torch::Tensor> ssim_forward(const torch::Tensor& image, const torch::Tensor& target,
                                        const torch::Tensor& window, bool need_grad) {
  check_images(image, target, window);
  if (image.scalar_type() == torch::kDouble) return forward_impl<double>(image, target, window, need_grad);
  return forward_impl<float>(image, target, window, need_grad);
}

// dL/d image [N, H, W, C] for dL/d(mean SSIM) = grad.
torch::Tensor ssim_backward(double grad, const torch::Tensor& image, const torch::Tensor& target,
                            const torch::Tensor& window, const torch::Tensor& coefficients) {
  check_images(image, target, window);
  check_input(coefficients, "coefficients", 4, image.scalar_type());
  if (image.scalar_type() == torch::kDouble) return backward_impl<double>(grad, image, target, window, coefficients);
  return backward_impl<float>(grad, image, target, window, coefficients);
}

}  // namespace

PYBIND11_MODULE(TORCH_EXTENSION_NAME, module) {
  module.doc() = "geoavatar native CPU SSIM (imaging layer)";
  using geoavatar_native::release_gil;
  module.def("ssim_forward", &ssim_forward, "mean SSIM and its per-pixel coefficients", release_gil());
  module.def("ssim_backward", &ssim_backward, "grad of the first image", release_gil());
}
