// Native CPU loops of the avatar layer (avatar/fused.py): Gaussians placed on their faces, and the polar
// coordinates of their local means. Built on first use by geoavatar.native like the renderer's kernels, and
// loaded by fused.py; the renderer knows nothing of faces. The face table is the avatar's own [M, 17] layout
// (fused.TABLE_WIDTH): R row-major (9), C (3), k (1), face quaternion (4).

#include "cpu_common.h"  // torch headers, threads_for_torch, parallel_over, check_input (geoavatar/native/csrc)

#include <cmath>
#include <cstdint>
#include <memory>
#include <vector>

namespace {

using namespace geoavatar_native;

// ----------------------------------------------------------------------------- face placement
// fused.py's _PlaceGaussians on CPU (fused.py documents the maths): mu_g = k R mu + C,
// q_g = q_face (x) q / |q|, s_g = k exp(s) for every (batch, Gaussian), and the backward, in one loop
// over the Gaussians each. In PyTorch the same maths is some 30 ops forward and 40 backward over [N]
// rows plus layout copies: 15 % of a 1-thread training step at 100k Gaussians. Each row of `index`
// ([B * N], row b * N + i for Gaussian i of batch b) is the face table's row (table [M, 17]: R
// row-major, C, k, face quaternion). The sums are written in the torch code's order; exp is libm's.

constexpr int kFaceRow = 17;

template <typename T>
inline void quaternion_product(const T* a, const T* b, T* out) {
  out[0] = a[0] * b[0] - a[1] * b[1] - a[2] * b[2] - a[3] * b[3];
  out[1] = a[0] * b[1] + a[1] * b[0] + a[2] * b[3] - a[3] * b[2];
  out[2] = a[0] * b[2] - a[1] * b[3] + a[2] * b[0] + a[3] * b[1];
  out[3] = a[0] * b[3] + a[1] * b[2] - a[2] * b[1] + a[3] * b[0];
}

// |q| floored at fused._EPS (clamp_min: NaN stays NaN)
template <typename T>
inline T floored_norm(const T* q) {
  const T norm = std::sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
  return norm < T(1e-12) ? T(1e-12) : norm;
}

void check_placement(const torch::Tensor& table, const torch::Tensor& means, const torch::Tensor& quats,
                     const torch::Tensor& log_scales, const torch::Tensor& index, bool check_index) {
  const auto dtype = means.scalar_type();
  check_input(table, "table", 2, dtype);
  check_input(means, "means", 2, dtype);
  check_input(quats, "quats", 2, dtype);
  check_input(log_scales, "log_scales", 2, dtype);
  check_input(index, "index", 1, torch::kInt64);
  TORCH_CHECK(table.size(1) == kFaceRow && means.size(1) == 3 && quats.size(1) == 4 && log_scales.size(1) == 3 &&
              quats.size(0) == means.size(0) && log_scales.size(0) == means.size(0),
              "place_gaussians: table [M, 17], means [N, 3], quats [N, 4], log_scales [N, 3] expected");
  const int64_t n = means.size(0);
  TORCH_CHECK(n > 0 ? index.numel() % n == 0 : index.numel() == 0, "place_gaussians: index must be [B * N]");
  if (check_index && index.numel() > 0) {  // the backward gets the forward's index
    TORCH_CHECK(index.min().item<int64_t>() >= 0 && index.max().item<int64_t>() < table.size(0),
                "place_gaussians: index out of the table's rows");
  }
}

// Per Gaussian: q / |q| (4), exp(s) (3), |q| floored (1), kept by the forward for the backward (it
// saves 3 exp, a sqrt and 4 divisions per Gaussian there).
constexpr int kPlacementAux = 8;

// Returns means [B * N, 3], quats [B * N, 4], scales [B * N, 3] and the aux rows [N, 8] for place_backward.
std::vector<torch::Tensor> place_forward(const torch::Tensor& table, const torch::Tensor& means,
                                         const torch::Tensor& quats, const torch::Tensor& log_scales,
                                         const torch::Tensor& index) {
  check_placement(table, means, quats, log_scales, index, true);
  const int64_t rows = index.numel(), n = means.size(0);
  auto opts = means.options();
  torch::Tensor means_g = torch::empty({rows, 3}, opts), quats_g = torch::empty({rows, 4}, opts);
  torch::Tensor scales_g = torch::empty({rows, 3}, opts), aux = torch::empty({n, kPlacementAux}, opts);
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "place_forward", [&] {
    using T = scalar_t;
    const T *tab = table.data_ptr<T>(), *mp = means.data_ptr<T>(), *qp = quats.data_ptr<T>();
    const T* sp = log_scales.data_ptr<T>();
    const int64_t* idx = index.data_ptr<int64_t>();
    T *mo = means_g.data_ptr<T>(), *qo = quats_g.data_ptr<T>(), *so = scales_g.data_ptr<T>();
    T* ax = aux.data_ptr<T>();
    parallel_over(n, [&](int64_t i) {
      const T* q = qp + 4 * i;
      T* a = ax + kPlacementAux * i;  // unit [0, 4), exp(s) [4, 7), norm 7
      a[7] = floored_norm(q);
      for (int c = 0; c < 4; ++c) a[c] = q[c] / a[7];
      for (int c = 0; c < 3; ++c) a[4 + c] = std::exp(sp[3 * i + c]);
      const T* mu = mp + 3 * i;
      for (int64_t row = i; row < rows; row += n) {  // batch b: row b * N + i
        const T* f = tab + kFaceRow * idx[row];  // R [0, 9), C [9, 12), k 12, face quaternion [13, 17)
        const T k = f[12];
        for (int r = 0; r < 3; ++r)
          mo[3 * row + r] = k * (f[3 * r] * mu[0] + f[3 * r + 1] * mu[1] + f[3 * r + 2] * mu[2]) + f[9 + r];
        quaternion_product(f + 13, a, qo + 4 * row);
        for (int c = 0; c < 3; ++c) so[3 * row + c] = k * a[4 + c];
      }
    });
  });
  return {means_g, quats_g, scales_g, aux};
}

// Returns the gradients of table [M, 17] (empty unless table_grad), means [N, 3], quats [N, 4],
// log_scales [N, 3]; the face rows are summed in row order (deterministic for any thread count).
std::vector<torch::Tensor> place_backward(const torch::Tensor& table, const torch::Tensor& means,
                                          const torch::Tensor& quats, const torch::Tensor& log_scales,
                                          const torch::Tensor& index, const torch::Tensor& aux,
                                          const torch::Tensor& g_means,
                                          const torch::Tensor& g_quats, const torch::Tensor& g_scales,
                                          bool table_grad) {
  check_placement(table, means, quats, log_scales, index, false);
  const int64_t rows = index.numel(), n = means.size(0), batch = n > 0 ? rows / n : 0;
  check_input(aux, "aux", 2, means.scalar_type());
  TORCH_CHECK(aux.size(0) == n && aux.size(1) == kPlacementAux, "place_gaussians: aux must be place_forward's");
  check_input(g_means, "g_means", 2, means.scalar_type());
  check_input(g_quats, "g_quats", 2, means.scalar_type());
  check_input(g_scales, "g_scales", 2, means.scalar_type());
  TORCH_CHECK(g_means.size(0) == rows && g_quats.size(0) == rows && g_scales.size(0) == rows,
              "place_gaussians: gradients must be [B * N, ...]");
  auto opts = means.options();
  torch::Tensor gm = torch::empty({n, 3}, opts), gq = torch::empty({n, 4}, opts), gs = torch::empty({n, 3}, opts);
  torch::Tensor g_table = table_grad ? torch::zeros({table.size(0), kFaceRow}, opts) : torch::empty({0}, opts);
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "place_backward", [&] {
    using T = scalar_t;
    const T *tab = table.data_ptr<T>(), *mp = means.data_ptr<T>();  // quats, log_scales: through aux
    const int64_t* idx = index.data_ptr<int64_t>();
    const T *gmp = g_means.data_ptr<T>(), *gqp = g_quats.data_ptr<T>(), *gsp = g_scales.data_ptr<T>();
    T *gmo = gm.data_ptr<T>(), *gqo = gq.data_ptr<T>(), *gso = gs.data_ptr<T>();
    const T* ax = aux.data_ptr<T>();
    // per row: the face row's gradient, summed into g_table below
    std::unique_ptr<T[]> per_row(table_grad ? new T[static_cast<size_t>(kFaceRow) * rows] : nullptr);
    parallel_over(n, [&](int64_t i) {
      const T* mu = mp + 3 * i;
      const T* unit = ax + kPlacementAux * i;
      const T* exp_s = unit + 4;
      const T norm = unit[7];
      T g_mu[3] = {0, 0, 0}, g_unit[4] = {0, 0, 0, 0}, g_ks[3] = {0, 0, 0};
      for (int64_t b = 0; b < batch; ++b) {
        const int64_t row = b * n + i;
        const T* f = tab + kFaceRow * idx[row];
        const T k = f[12];
        const T* g = gmp + 3 * row;
        const T* gqr = gqp + 4 * row;
        const T* gsr = gsp + 3 * row;
        const T kg[3] = {k * g[0], k * g[1], k * g[2]};
        for (int c = 0; c < 3; ++c) g_mu[c] += f[c] * kg[0] + f[3 + c] * kg[1] + f[6 + c] * kg[2];  // R^T k g
        const T conj_face[4] = {f[13], -f[14], -f[15], -f[16]};
        T d_unit[4];
        quaternion_product(conj_face, gqr, d_unit);  // d(a (x) b)/db = conj(a) (x) g
        for (int c = 0; c < 4; ++c) g_unit[c] += d_unit[c];
        for (int c = 0; c < 3; ++c) g_ks[c] += gsr[c] * k;
        if (table_grad) {
          T* out = per_row.get() + kFaceRow * row;
          for (int r = 0; r < 3; ++r)
            for (int c = 0; c < 3; ++c) out[3 * r + c] = kg[r] * mu[c];  // dR = k g mu^T
          T dk = 0;
          for (int r = 0; r < 3; ++r) {
            out[9 + r] = g[r];  // dC
            dk += g[r] * (f[3 * r] * mu[0] + f[3 * r + 1] * mu[1] + f[3 * r + 2] * mu[2]);
          }
          out[12] = dk + (gsr[0] * exp_s[0] + gsr[1] * exp_s[1] + gsr[2] * exp_s[2]);  // dk
          const T conj_unit[4] = {unit[0], -unit[1], -unit[2], -unit[3]};
          quaternion_product(gqr, conj_unit, out + 13);  // d(a (x) b)/da = g (x) conj(b)
        }
      }
      for (int c = 0; c < 3; ++c) gmo[3 * i + c] = g_mu[c];
      // normalize's backward: (g - u (u . g)) / |q|, and g / eps where the norm was floored
      const T dot = unit[0] * g_unit[0] + unit[1] * g_unit[1] + unit[2] * g_unit[2] + unit[3] * g_unit[3];
      const T radial = norm > T(1e-12) ? dot : T(0);
      for (int c = 0; c < 4; ++c) gqo[4 * i + c] = (g_unit[c] - unit[c] * radial) / norm;
      for (int c = 0; c < 3; ++c) gso[3 * i + c] = g_ks[c] * exp_s[c];
    });
    if (table_grad) {
      T* gt = g_table.data_ptr<T>();
      const T* per = per_row.get();
      for (int64_t row = 0; row < rows; ++row) {
        T* out = gt + kFaceRow * idx[row];
        for (int j = 0; j < kFaceRow; ++j) out[j] += per[kFaceRow * row + j];
      }
    }
  });
  return {g_table, gm, gq, gs};
}

// ----------------------------------------------------------------------------- polar coordinates
// fused.py's _PolarCoordinates on CPU (binding.polar_coordinates documents it): r = |mu|,
// phi = atan2(|mu_tangent|, mu_normal) (|mu_normal| when two-sided), phi = 0 at the origin; one loop
// each way instead of ~25 PyTorch ops over [N] (3 % of a 1-thread training step at 100k Gaussians).
// Local axis 1 is the normal (fused.NORMAL_AXIS), 0 and 2 the tangent plane.

// Returns r [N], phi [N].
std::vector<torch::Tensor> polar_forward(const torch::Tensor& means, bool two_sided) {
  check_input(means, "means", 2, means.scalar_type());
  TORCH_CHECK(means.size(1) == 3, "polar_coordinates: means must be [N, 3]");
  const int64_t n = means.size(0);
  torch::Tensor r = torch::empty({n}, means.options()), phi = torch::empty({n}, means.options());
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "polar_forward", [&] {
    using T = scalar_t;
    const T* mu = means.data_ptr<T>();
    T *ro = r.data_ptr<T>(), *po = phi.data_ptr<T>();
    parallel_over(n, [&](int64_t i) {
      const T x = mu[3 * i], y = mu[3 * i + 1], z = mu[3 * i + 2];
      const T radius = std::sqrt(x * x + y * y + z * z);
      const bool tiny = radius <= T(1e-12);
      const T normal = tiny ? T(1) : (two_sided ? std::abs(y) : y);
      const T tangent = tiny ? T(0) : std::sqrt(x * x + z * z);
      ro[i] = radius;
      po[i] = std::atan2(tangent, normal);
    });
  });
  return {r, phi};
}

// Returns the gradient of means [N, 3] (vector_norm's zero subgradient at 0; no angle gradient there).
torch::Tensor polar_backward(const torch::Tensor& means, const torch::Tensor& g_r, const torch::Tensor& g_phi,
                             bool two_sided) {
  check_input(means, "means", 2, means.scalar_type());
  check_input(g_r, "g_r", 1, means.scalar_type());
  check_input(g_phi, "g_phi", 1, means.scalar_type());
  const int64_t n = means.size(0);
  TORCH_CHECK(means.size(1) == 3 && g_r.numel() == n && g_phi.numel() == n, "polar_coordinates: shapes differ");
  torch::Tensor grad = torch::empty({n, 3}, means.options());
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "polar_backward", [&] {
    using T = scalar_t;
    const T *mu = means.data_ptr<T>(), *gr = g_r.data_ptr<T>(), *gp = g_phi.data_ptr<T>();
    T* out = grad.data_ptr<T>();
    parallel_over(n, [&](int64_t i) {
      const T x = mu[3 * i], y = mu[3 * i + 1], z = mu[3 * i + 2];
      const T radius = std::sqrt(x * x + y * y + z * z);
      const bool live = radius > T(1e-12);
      const T normal = live ? (two_sided ? std::abs(y) : y) : T(1);
      const T tangent = live ? std::sqrt(x * x + z * z) : T(0);
      const T along = radius > 0 ? gr[i] / radius : T(0);  // d r = mu / r
      // atan2(t, n): d t = n / (t^2 + n^2), d n = -t / (t^2 + n^2)
      const T g = (live ? gp[i] : T(0)) / (live ? tangent * tangent + normal * normal : T(1));
      const T g_t = tangent > 0 ? g * normal / tangent : T(0);  // d t = mu_t / t
      T g_n = -g * tangent;
      if (two_sided) g_n = g_n * static_cast<T>((y > 0) - (y < 0));  // sign(mu_normal)
      out[3 * i] = along * x + g_t * x;
      out[3 * i + 1] = along * y + g_n;
      out[3 * i + 2] = along * z + g_t * z;
    });
  });
  return grad;
}

// ----------------------------------------------------------------------------- surface splats
// fused._SurfaceSplatsCPU: one Gaussian at each face's centroid, its std from the face's area and its colour an
// albedo shaded by SH lighting of the face normal (prep/photometric.SurfaceAppearance, the tracker's appearance
// model, with one Gaussian per face). In PyTorch that is ~25 ops forward and ~40 backward over [F] rows and the
// gather of the three corners: ~6 ms of a frame's ~18 ms in the photometric fit at 8k faces on one thread.
// Per face with corners a, b, c: centre = (a + b + c) / 3, x = (b - a) x (c - a), d = sqrt(max(|x|^2, 1e-16)),
// n = x / d, std = size sqrt(d / 2), colour = albedo (Y(n) L) with Y the real SH basis of bands 0-2 (photometric.
// sh_basis: the constants below) and L the lighting [9, 3].

constexpr double kShC0 = 0.28209479177387814, kShC1 = 0.4886025119029199;
constexpr double kShC2a = 1.0925484305920792, kShC2b = 0.31539156525252005, kShC2c = 0.5462742152960396;

template <typename T>
inline void sh_basis(T x, T y, T z, T* b) {
  b[0] = T(kShC0);
  b[1] = -T(kShC1) * y;
  b[2] = T(kShC1) * z;
  b[3] = -T(kShC1) * x;
  b[4] = T(kShC2a) * x * y;
  b[5] = -T(kShC2a) * y * z;
  b[6] = T(kShC2b) * (T(3) * z * z - T(1));
  b[7] = -T(kShC2a) * x * z;
  b[8] = T(kShC2c) * (x * x - y * y);
}

// `face_range`: also check that every face names a row of vertices (the forward; the backward gets the same faces).
void check_surface(const torch::Tensor& vertices, const torch::Tensor& faces, const torch::Tensor& albedo,
                   const torch::Tensor& light, bool face_range) {
  const auto dtype = vertices.scalar_type();
  check_input(vertices, "vertices", 2, dtype);
  check_input(faces, "faces", 2, torch::kLong);
  check_input(albedo, "albedo", 2, dtype);
  check_input(light, "light", 2, dtype);
  TORCH_CHECK(vertices.size(1) == 3 && faces.size(1) == 3,
              "surface_splats: vertices and faces must be [K, 3], [F, 3]");
  TORCH_CHECK(albedo.size(0) == faces.size(0) && albedo.size(1) == 3, "surface_splats: albedo must be [F, 3]");
  TORCH_CHECK(light.size(0) == 9 && light.size(1) == 3, "surface_splats: light must be [9, 3]");
  if (face_range && faces.numel() > 0) {
    const auto range = torch::aminmax(faces);
    TORCH_CHECK(std::get<0>(range).item<int64_t>() >= 0 && std::get<1>(range).item<int64_t>() < vertices.size(0),
                "surface_splats: a face names a vertex outside vertices");
  }
}

// Returns centres [F, 3], std [F], colours [F, 3] and per face (n, d) [F, 4] for surface_backward.
std::vector<torch::Tensor> surface_forward(const torch::Tensor& vertices, const torch::Tensor& faces,
                                           const torch::Tensor& albedo, const torch::Tensor& light, double size) {
  check_surface(vertices, faces, albedo, light, true);
  const int64_t count = faces.size(0);
  auto options = vertices.options();
  torch::Tensor centres = torch::empty({count, 3}, options), std_out = torch::empty({count}, options);
  torch::Tensor colours = torch::empty({count, 3}, options), frames = torch::empty({count, 4}, options);
  AT_DISPATCH_FLOATING_TYPES(vertices.scalar_type(), "surface_forward", [&] {
    using T = scalar_t;
    const T *v = vertices.data_ptr<T>(), *alb = albedo.data_ptr<T>(), *L = light.data_ptr<T>();
    const int64_t* f = faces.data_ptr<int64_t>();
    T *co = centres.data_ptr<T>(), *so = std_out.data_ptr<T>(), *cl = colours.data_ptr<T>();
    T* fr = frames.data_ptr<T>();
    const T third = T(1) / T(3);  // the barycentric weight of SurfaceAppearance.bary, rounded as it is
    parallel_over(count, [&](int64_t i) {
      const T *a = v + 3 * f[3 * i], *b = v + 3 * f[3 * i + 1], *c = v + 3 * f[3 * i + 2];
      T e1[3], e2[3];
      for (int k = 0; k < 3; ++k) {
        co[3 * i + k] = third * a[k] + third * b[k] + third * c[k];
        e1[k] = b[k] - a[k];
        e2[k] = c[k] - a[k];
      }
      const T x = e1[1] * e2[2] - e1[2] * e2[1], y = e1[2] * e2[0] - e1[0] * e2[2];
      const T z = e1[0] * e2[1] - e1[1] * e2[0];
      const T d = std::sqrt(std::max(x * x + y * y + z * z, T(1e-16)));
      const T n[3] = {x / d, y / d, z / d};
      so[i] = T(size) * std::sqrt(T(0.5) * d);
      T basis[9];
      sh_basis(n[0], n[1], n[2], basis);
      for (int k = 0; k < 3; ++k) {
        T shade = 0;
        for (int j = 0; j < 9; ++j) shade += basis[j] * L[3 * j + k];
        cl[3 * i + k] = alb[3 * i + k] * shade;
        fr[4 * i + k] = n[k];
      }
      fr[4 * i + 3] = d;
    });
  });
  return {centres, std_out, colours, frames};
}

// Returns the gradients of vertices [K, 3], albedo [F, 3], light [9, 3]; one loop in face order (deterministic:
// the vertex and lighting sums add the faces in that order).
std::vector<torch::Tensor> surface_backward(const torch::Tensor& vertices, const torch::Tensor& faces,
                                            const torch::Tensor& albedo, const torch::Tensor& light,
                                            const torch::Tensor& frames, const torch::Tensor& g_centres,
                                            const torch::Tensor& g_std, const torch::Tensor& g_colours, double size) {
  check_surface(vertices, faces, albedo, light, false);
  const auto dtype = vertices.scalar_type();
  check_input(frames, "frames", 2, dtype);
  check_input(g_centres, "g_centres", 2, dtype);
  check_input(g_std, "g_std", 1, dtype);
  check_input(g_colours, "g_colours", 2, dtype);
  const int64_t count = faces.size(0);
  TORCH_CHECK(frames.size(0) == count && g_centres.size(0) == count && g_std.size(0) == count &&
                  g_colours.size(0) == count, "surface_splats: gradient rows differ from the faces");
  torch::Tensor g_vertices = torch::zeros_like(vertices), g_albedo = torch::empty_like(albedo);
  torch::Tensor g_light = torch::zeros_like(light);
  AT_DISPATCH_FLOATING_TYPES(dtype, "surface_backward", [&] {
    using T = scalar_t;
    const T *v = vertices.data_ptr<T>(), *alb = albedo.data_ptr<T>(), *L = light.data_ptr<T>();
    const T *fr = frames.data_ptr<T>(), *gc = g_centres.data_ptr<T>(), *gs = g_std.data_ptr<T>();
    const T* gcol = g_colours.data_ptr<T>();
    const int64_t* f = faces.data_ptr<int64_t>();
    T *gv = g_vertices.data_ptr<T>(), *ga = g_albedo.data_ptr<T>(), *gl = g_light.data_ptr<T>();
    for (int64_t i = 0; i < count; ++i) {
      const T n[3] = {fr[4 * i], fr[4 * i + 1], fr[4 * i + 2]}, d = fr[4 * i + 3];
      T basis[9], g_basis[9] = {0, 0, 0, 0, 0, 0, 0, 0, 0};
      sh_basis(n[0], n[1], n[2], basis);
      for (int k = 0; k < 3; ++k) {
        T shade = 0;
        for (int j = 0; j < 9; ++j) shade += basis[j] * L[3 * j + k];
        ga[3 * i + k] = gcol[3 * i + k] * shade;
        const T g_shade = gcol[3 * i + k] * alb[3 * i + k];
        for (int j = 0; j < 9; ++j) {
          gl[3 * j + k] += basis[j] * g_shade;
          g_basis[j] += L[3 * j + k] * g_shade;
        }
      }
      // d Y / d n, transposed
      const T c1 = T(kShC1), c2a = T(kShC2a), c2b = T(kShC2b), c2c = T(kShC2c);
      const T g_n[3] = {
          -c1 * g_basis[3] + c2a * n[1] * g_basis[4] - c2a * n[2] * g_basis[7] + T(2) * c2c * n[0] * g_basis[8],
          -c1 * g_basis[1] + c2a * n[0] * g_basis[4] - c2a * n[2] * g_basis[5] - T(2) * c2c * n[1] * g_basis[8],
          c1 * g_basis[2] - c2a * n[1] * g_basis[5] + T(6) * c2b * n[2] * g_basis[6] - c2a * n[0] * g_basis[7]};
      // std = size sqrt(d / 2): d std / d d = std / (2 d); n = x / d, d = |x| (0 below the floor)
      const T along = g_n[0] * n[0] + g_n[1] * n[1] + g_n[2] * n[2];
      const T g_d = gs[i] * T(size) * std::sqrt(T(0.5) * d) / (T(2) * d) - along / d;
      const int64_t ia = f[3 * i], ib = f[3 * i + 1], ic = f[3 * i + 2];
      const T *a = v + 3 * ia, *b = v + 3 * ib, *c = v + 3 * ic;
      const T e1[3] = {b[0] - a[0], b[1] - a[1], b[2] - a[2]}, e2[3] = {c[0] - a[0], c[1] - a[1], c[2] - a[2]};
      const T x[3] = {e1[1] * e2[2] - e1[2] * e2[1], e1[2] * e2[0] - e1[0] * e2[2], e1[0] * e2[1] - e1[1] * e2[0]};
      const bool floored = x[0] * x[0] + x[1] * x[1] + x[2] * x[2] < T(1e-16);  // clamp_min: no gradient below
      T g_x[3];
      for (int k = 0; k < 3; ++k) g_x[k] = g_n[k] / d + (floored ? T(0) : g_d * x[k] / d);
      // x = e1 x e2: d e1 = e2 x g_x, d e2 = g_x x e1
      const T g_e1[3] = {e2[1] * g_x[2] - e2[2] * g_x[1], e2[2] * g_x[0] - e2[0] * g_x[2],
                         e2[0] * g_x[1] - e2[1] * g_x[0]};
      const T g_e2[3] = {g_x[1] * e1[2] - g_x[2] * e1[1], g_x[2] * e1[0] - g_x[0] * e1[2],
                         g_x[0] * e1[1] - g_x[1] * e1[0]};
      for (int k = 0; k < 3; ++k) {
        const T share = T(1) / T(3) * gc[3 * i + k];  // each corner's part of the centroid's gradient
        gv[3 * ia + k] += share - g_e1[k] - g_e2[k];
        gv[3 * ib + k] += share + g_e1[k];
        gv[3 * ic + k] += share + g_e2[k];
      }
    }
  });
  return {g_vertices, g_albedo, g_light};
}

}  // namespace

PYBIND11_MODULE(TORCH_EXTENSION_NAME, module) {
  module.doc() = "geoavatar native CPU face placement, polar coordinates and surface splats (avatar layer)";
  using geoavatar_native::release_gil;
  module.def("place_forward", &place_forward, "fused._PlaceGaussians: global means, quats, scales", release_gil());
  module.def("place_backward", &place_backward, "grads of the face table, means, quats, log_scales", release_gil());
  module.def("polar_forward", &polar_forward, "fused._PolarCoordinates: r, phi", release_gil());
  module.def("polar_backward", &polar_backward, "grad of the local means", release_gil());
  module.def("surface_forward", &surface_forward, "fused._SurfaceSplatsCPU: centres, std, colours, (n, d)",
             release_gil());
  module.def("surface_backward", &surface_backward, "grads of the vertices, albedo, light", release_gil());
}
