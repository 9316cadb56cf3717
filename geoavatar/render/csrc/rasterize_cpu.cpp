// Native CPU rasterize-to-pixels for geoavatar.render (backend "cpu").
//
// The same split as gsplat: projection (EWA, culling, radii) stays in PyTorch (torch_backend.py) and
// this file does the per-pixel work that the PyTorch backend spends its time on:
//   bin_gaussians  - visible Gaussians sorted front to back (depth, then index, like the torch
//                    backend's stable argsort), then a counting sort by tile, so every tile's list is
//                    in depth order; only tiles holding a pixel centre of the Gaussian's box get it.
//   forward        - per tile (OpenMP, dynamic schedule), Gaussians front to back over the pixels of
//                    their box: alpha = min(0.999, o exp(-sigma)), alpha < 1/255 skipped, a pixel
//                    stops before the Gaussian that would take T to <= 1e-4; the tile stops when all
//                    its pixels have. Keeps T_final and, per pixel, the end of its composited range.
//   backward       - per tile, back to front from T_final, recovering T by division as gsplat does,
//                    with a running sum of what lies behind; gradients per (tile, Gaussian) entry,
//                    then summed per Gaussian in a fixed order (deterministic for any thread count).
// Two implementations of forward and backward, chosen per call (cpu_backend.simd_path()):
//   scalar         - pixel by pixel with libm's exp, per-pixel state (T, colour sums, the running sums
//                    of backward) in double; float64 inputs always take it (gradcheck).
//   avx512 / avx2 / vector - float32 only, the same arithmetic per pixel: "vector" steps a Gaussian
//                    over W pixels of a row of its tile (see "float32 lanes" below) in GCC/Clang vector
//                    types for the baseline ISA (NEON on aarch64, SSE2 on x86-64); "avx512" and "avx2"
//                    step it over a 4 x 4 pixel block, one kernel source in intrinsics ("block lanes":
//                    one zmm, or two ymm, per block, masks as bits);
//                    picked at run time; forward and backward state is float32.
// Outside its box a Gaussian's alpha is below 1/255 (see torch_backend.py), so only box pixels count.
//
// Beside the Gaussians, mesh_zbuffer: the scan of render/mesh.py's triangle z-buffer (head pictures, prepare's
// overlay video, synthetic subjects), mesh.py's PyTorch candidate loop as one serial loop over the triangles.

#include "cpu_common.h"  // torch headers, threads_for_torch, parallel_over, check_input (geoavatar/native/csrc)

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <memory>
#include <numeric>
#include <string>
#include <type_traits>
#include <vector>

#if defined(__GNUC__) && (defined(__x86_64__) || defined(__i386__))
#include <immintrin.h>  // the AVX-512 lane kernels (masks in k registers)
#endif

namespace {

using namespace geoavatar_native;

constexpr double kAlphaMin = 1.0 / 255.0;
constexpr double kAlphaMax = 0.999;
constexpr double kTransmittanceMin = 1e-4;

// One visible Gaussian, gathered once so the tile loops read one contiguous record.
template <typename scalar_t>
struct Splat {
  scalar_t mx, my;     // mean in pixels
  scalar_t a, b, c;    // conic [[a, b], [b, c]]
  scalar_t opacity;
  scalar_t sigma_cut;  // sigma above which o exp(-sigma) < 1/255 surely (a cheap test before exp)
  scalar_t r, g, bl;   // colour
  int32_t x0, x1, y0, y1;  // pixel box (inclusive), clipped to the image
  int32_t tx0, tx1, ty0, ty1;  // tiles of the box (inclusive): divided here, in parallel, not in binning
};

// Pixel rectangle of one tile: origin and size (tiles on the right and bottom edges may be cut).
struct TileRect {
  int64_t x0, y0, w, h;
};

struct Grid {
  int64_t width, height, tile, tiles_x, tiles_y;
  int64_t n_tiles() const { return tiles_x * tiles_y; }
  TileRect rect(int64_t index) const {
    const int64_t x0 = (index % tiles_x) * tile, y0 = (index / tiles_x) * tile;
    return {x0, y0, std::min(tile, width - x0), std::min(tile, height - y0)};
  }
};

// The tiles in the order the threads take them (dynamic schedule): most entries first, so that the
// last ones handed out are small and the threads finish together (longest-processing-time first; with
// 64 tiles at tile size 32 the largest holds ~11 % of the work). Ties by index; any order gives the same
// results, each tile is computed alone.
std::vector<int32_t> tiles_by_work(const int64_t* offsets, int64_t n_tiles) {
  std::vector<int32_t> order(n_tiles);
  std::iota(order.begin(), order.end(), 0);
  std::stable_sort(order.begin(), order.end(), [offsets](int32_t i, int32_t j) {
    return offsets[i + 1] - offsets[i] > offsets[j + 1] - offsets[j];
  });
  return order;
}

// Fills splats [N] (the forward's buffer, handed to the backward as a byte tensor: not gathered twice).
template <typename scalar_t>
void gather_splats(const torch::Tensor& means2d, const torch::Tensor& conics, const torch::Tensor& opacities,
                   const torch::Tensor& colors, const torch::Tensor& radii, const Grid& grid,
                   Splat<scalar_t>* splats) {
  const int64_t n = means2d.size(0);
  const scalar_t* m = means2d.data_ptr<scalar_t>();
  const scalar_t* q = conics.data_ptr<scalar_t>();
  const scalar_t* o = opacities.data_ptr<scalar_t>();
  const scalar_t* col = colors.data_ptr<scalar_t>();
  const int32_t* rad = radii.data_ptr<int32_t>();
#pragma omp parallel for schedule(static) num_threads(threads_for_torch())
  for (int64_t i = 0; i < n; ++i) {
    Splat<scalar_t>& s = splats[i];
    s.mx = m[2 * i];
    s.my = m[2 * i + 1];
    s.a = q[3 * i];
    s.b = q[3 * i + 1];
    s.c = q[3 * i + 2];
    s.opacity = o[i];
    // margin: the exact test on alpha decides; this one only skips exp far from the threshold
    s.sigma_cut = s.opacity > 0 ? static_cast<scalar_t>(std::log(255.0 * static_cast<double>(s.opacity)) + 1e-3)
                                : static_cast<scalar_t>(-1);
    s.r = col[3 * i];
    s.g = col[3 * i + 1];
    s.bl = col[3 * i + 2];
    const int32_t rx = rad[2 * i], ry = rad[2 * i + 1];
    if (rx <= 0 && ry <= 0) {  // culled by the projection
      s.x0 = 0, s.x1 = -1, s.y0 = 0, s.y1 = -1;
      s.tx0 = 0, s.tx1 = -1, s.ty0 = 0, s.ty1 = -1;
      continue;
    }
    // pixel centres j + 0.5 inside [mx - rx, mx + rx]
    double fx0 = std::ceil(static_cast<double>(s.mx) - rx - 0.5);
    double fx1 = std::floor(static_cast<double>(s.mx) + rx - 0.5);
    double fy0 = std::ceil(static_cast<double>(s.my) - ry - 0.5);
    double fy1 = std::floor(static_cast<double>(s.my) + ry - 0.5);
    // The box is cut to the bounding box of the ellipse sigma <= sigma_cut, with RowSpan's margins
    // (cut + 1e-3, 0.01 px): outside it alpha < 1/255, so no pixel changes. The integer radii round
    // up and the 3-sigma square is wider than the tilted ellipse: at 256^2 with ~100k small Gaussians
    // this halves the rows the tile loops visit and drops ~8 % of the (tile, Gaussian) entries.
    const double ca = s.a, cb = s.b, cc = s.c, det = ca * cc - cb * cb;
    const double cut = static_cast<double>(s.sigma_cut) + 1e-3;
    if (ca > 0 && det > 0 && std::isfinite(cut) && std::isfinite(static_cast<double>(s.mx)) &&
        std::isfinite(static_cast<double>(s.my))) {
      if (cut < 0) {  // sigma >= 0 > cut everywhere
        fx1 = fx0 - 1;
      } else {
        // sigma = 0.5 (a dx^2 + 2 b dx dy + c dy^2) <= cut reaches |dx| <= sqrt(2 cut c / det), |dy| likewise
        const double hx = std::sqrt(2.0 * cut * cc / det), hy = std::sqrt(2.0 * cut * ca / det);
        fx0 = std::max(fx0, std::ceil(static_cast<double>(s.mx) - hx - 0.5 - 0.01));
        fx1 = std::min(fx1, std::floor(static_cast<double>(s.mx) + hx - 0.5 + 0.01));
        fy0 = std::max(fy0, std::ceil(static_cast<double>(s.my) - hy - 0.5 - 0.01));
        fy1 = std::min(fy1, std::floor(static_cast<double>(s.my) + hy - 0.5 + 0.01));
      }
    }
    s.x0 = static_cast<int32_t>(std::max(fx0, 0.0));
    s.x1 = static_cast<int32_t>(std::min(fx1, static_cast<double>(grid.width - 1)));
    s.y0 = static_cast<int32_t>(std::max(fy0, 0.0));
    s.y1 = static_cast<int32_t>(std::min(fy1, static_cast<double>(grid.height - 1)));
    s.tx0 = static_cast<int32_t>(s.x0 / grid.tile), s.tx1 = static_cast<int32_t>(s.x1 / grid.tile);
    s.ty0 = static_cast<int32_t>(s.y0 / grid.tile), s.ty1 = static_cast<int32_t>(s.y1 / grid.tile);
  }
}

// Sorts order (ascending indices) by depth, ties by index: the torch backend's stable argsort.
void sort_by_depth(std::vector<int32_t>& order, const double* z) {
  std::sort(order.begin(), order.end(), [z](int32_t i, int32_t j) { return z[i] < z[j] || (z[i] == z[j] && i < j); });
}

// float32 depths: a stable LSD radix sort (3 passes of 11 bits) on keys that order like the floats;
// stable on ascending indices, so ties stay in index order. A fifth of std::sort's time at 50k.
void sort_by_depth(std::vector<int32_t>& order, const float* z) {
  constexpr int kBits = 11, kBuckets = 1 << kBits;
  const size_t n = order.size();
  std::vector<uint32_t> keys(n), keys_next(n);
  std::vector<int32_t> next(n);
  for (size_t k = 0; k < n; ++k) {
    uint32_t bits;
    const float depth = z[order[k]] + 0.0f;  // -0 becomes +0: equal floats, equal keys
    std::memcpy(&bits, &depth, sizeof bits);
    keys[k] = bits & 0x80000000u ? ~bits : bits | 0x80000000u;  // negative: reversed; positive: above them
  }
  for (int shift = 0; shift < 32; shift += kBits) {
    std::vector<size_t> start(kBuckets + 1, 0);
    for (size_t k = 0; k < n; ++k) ++start[((keys[k] >> shift) & (kBuckets - 1)) + 1];
    std::partial_sum(start.begin(), start.end(), start.begin());
    for (size_t k = 0; k < n; ++k) {
      const size_t to = start[(keys[k] >> shift) & (kBuckets - 1)]++;
      keys_next[to] = keys[k];
      next[to] = order[k];
    }
    keys.swap(keys_next);
    order.swap(next);
  }
}

// Tile lists: offsets [T + 1] into ids [M], each tile's ids front to back. For the backward, each
// entry's slot [M] in a Gaussian-major order (Gaussian i's entries at firsts[i] .. firsts[i + 1] - 1,
// in tile order): it writes an entry's gradients there, so that the sum per Gaussian reads contiguous
// records and runs in parallel over Gaussians, in the same fixed order as before.
template <typename scalar_t>
void bin_gaussians(const Splat<scalar_t>* splats, int64_t n, const torch::Tensor& depths, const Grid& grid,
                   std::vector<int64_t>& offsets, std::vector<int32_t>& ids, torch::Tensor& slots_t,
                   int64_t* firsts) {
  // Visible Gaussians, their entries (firsts) and the entries per tile: one pass in index order, where
  // the splat records are read sequentially (tile counts do not depend on the order).
  std::vector<int32_t> order;
  order.reserve(n);
  std::vector<int64_t> counts(grid.n_tiles() + 1, 0);
  firsts[0] = 0;
  for (int64_t i = 0; i < n; ++i) {
    const auto& s = splats[i];
    const bool in = s.x0 <= s.x1 && s.y0 <= s.y1;
    firsts[i + 1] = firsts[i] + (in ? int64_t{s.tx1 - s.tx0 + 1} * (s.ty1 - s.ty0 + 1) : 0);
    if (!in) continue;
    order.push_back(static_cast<int32_t>(i));
    for (int64_t ty = s.ty0; ty <= s.ty1; ++ty)
      for (int64_t tx = s.tx0; tx <= s.tx1; ++tx) ++counts[ty * grid.tiles_x + tx + 1];
  }
  sort_by_depth(order, depths.data_ptr<scalar_t>());
  std::partial_sum(counts.begin(), counts.end(), counts.begin());
  offsets = counts;
  ids.resize(offsets.back());
  TORCH_CHECK(offsets.back() < INT32_MAX, "rasterize_cpu: too many (tile, Gaussian) entries");
  slots_t.resize_({offsets.back()});
  int32_t* slots = slots_t.data_ptr<int32_t>();
  std::vector<int64_t> cursor(offsets.begin(), offsets.end() - 1);
  // In depth order the records are read at random (7 MB at 100k Gaussians): each read missed the
  // cache, the top sample of the forward's serial part; fetch the tile range of the Gaussian 16 ahead.
  constexpr size_t kAhead = 16;
  const size_t visible = order.size();
  for (size_t j = 0; j < visible; ++j) {
    if (j + kAhead < visible) {
      const char* ahead = reinterpret_cast<const char*>(&splats[order[j + kAhead]].tx0);
      __builtin_prefetch(ahead);
      __builtin_prefetch(ahead + 4 * sizeof(int32_t) - 1);  // the range may straddle two lines
    }
    const int32_t i = order[j];
    const auto& s = splats[i];
    int32_t slot = static_cast<int32_t>(firsts[i]);
    for (int64_t ty = s.ty0; ty <= s.ty1; ++ty) {
      for (int64_t tx = s.tx0; tx <= s.tx1; ++tx) {
        const int64_t k = cursor[ty * grid.tiles_x + tx]++;
        ids[k] = i;
        slots[k] = slot++;
      }
    }
  }
}

template <typename scalar_t>
void forward_tiles_scalar(const Splat<scalar_t>* splats, const std::vector<int64_t>& offsets,
                   const std::vector<int32_t>& ids, const double* background, const Grid& grid, scalar_t* out_rgb,
                   scalar_t* out_alpha, int32_t* out_last, double* out_t_final) {
  const int64_t t = grid.tile, tp = t * t;
  const std::vector<int32_t> order = tiles_by_work(offsets.data(), grid.n_tiles());
#pragma omp parallel num_threads(threads_for_torch())
  {
    std::vector<double> trans(tp), rgb(3 * tp);
    std::vector<int32_t> last(tp);
    std::vector<uint8_t> done(tp);
#pragma omp for schedule(dynamic, 1)
    for (int64_t nth = 0; nth < grid.n_tiles(); ++nth) {
      const int64_t tile = order[nth];
      const TileRect r = grid.rect(tile);
      const int64_t tx0 = r.x0, ty0 = r.y0, tw = r.w, th = r.h;
      std::fill(trans.begin(), trans.end(), 1.0);
      std::fill(rgb.begin(), rgb.end(), 0.0);
      std::fill(last.begin(), last.end(), 0);
      std::fill(done.begin(), done.end(), 0);
      int64_t n_done = 0;
      const int64_t begin = offsets[tile], end = offsets[tile + 1];
      for (int64_t k = begin; k < end && n_done < tw * th; ++k) {
        const Splat<scalar_t>& s = splats[ids[k]];
        const int64_t x0 = std::max<int64_t>(s.x0, tx0), x1 = std::min<int64_t>(s.x1, tx0 + tw - 1);
        const int64_t y0 = std::max<int64_t>(s.y0, ty0), y1 = std::min<int64_t>(s.y1, ty0 + th - 1);
        for (int64_t y = y0; y <= y1; ++y) {
          const scalar_t dy = s.my - (static_cast<scalar_t>(y) + scalar_t(0.5));
          for (int64_t x = x0; x <= x1; ++x) {
            const int64_t p = (y - ty0) * t + (x - tx0);
            if (done[p]) continue;
            const scalar_t dx = s.mx - (static_cast<scalar_t>(x) + scalar_t(0.5));
            const scalar_t sigma = scalar_t(0.5) * (s.a * dx * dx + s.c * dy * dy) + s.b * dx * dy;
            if (sigma > s.sigma_cut) continue;
            const scalar_t alpha_raw = s.opacity * std::exp(-sigma);
            if (alpha_raw < static_cast<scalar_t>(kAlphaMin)) continue;
            const double alpha = std::min(static_cast<double>(alpha_raw), kAlphaMax);
            const double next_t = trans[p] * (1.0 - alpha);
            if (next_t <= kTransmittanceMin) {
              done[p] = 1;
              ++n_done;
              continue;
            }
            const double w = alpha * trans[p];
            rgb[3 * p] += w * s.r;
            rgb[3 * p + 1] += w * s.g;
            rgb[3 * p + 2] += w * s.bl;
            trans[p] = next_t;
            last[p] = static_cast<int32_t>(k - begin + 1);
          }
        }
      }
      for (int64_t y = 0; y < th; ++y) {
        for (int64_t x = 0; x < tw; ++x) {
          const int64_t p = y * t + x, pix = (ty0 + y) * grid.width + (tx0 + x);
          for (int ch = 0; ch < 3; ++ch)
            out_rgb[3 * pix + ch] = static_cast<scalar_t>(rgb[3 * p + ch] + trans[p] * background[ch]);
          out_alpha[pix] = static_cast<scalar_t>(1.0 - trans[p]);
          out_last[pix] = last[p];
          out_t_final[pix] = trans[p];
        }
      }
    }
  }
}

// Gradient record of one (tile, Gaussian) entry: means2d (2), conic (3), opacity, colour (3).
constexpr int kEntryGrads = 9;

// Entries behind every pixel's composited range get no gradient; their records are written here
// (entry_grads is not zero-filled: it holds ~15 MB at 100k Gaussians and every record is written once).
inline void zero_entries(double* entry_grads, const int32_t* slots, int64_t begin, int64_t end) {
  for (int64_t k = begin; k < end; ++k)
    std::fill_n(entry_grads + kEntryGrads * static_cast<int64_t>(slots[k]), kEntryGrads, 0.0);
}

// Backward of the scalar path (float32 and float64).
template <typename scalar_t>
void backward_tiles(const Splat<scalar_t>* splats, const int64_t* offsets, const int32_t* ids, const int32_t* slots,
                    const int32_t* last_in, const double* t_final, const scalar_t* grad_rgb,
                    const scalar_t* grad_alpha, const double* background, const Grid& grid, double* entry_grads) {
  const int64_t t = grid.tile, tp = t * t;
  const std::vector<int32_t> order = tiles_by_work(offsets, grid.n_tiles());
#pragma omp parallel num_threads(threads_for_torch())
  {
    std::vector<double> trans(tp), behind(tp), g(3 * tp);
    std::vector<int32_t> last(tp);
#pragma omp for schedule(dynamic, 1)
    for (int64_t nth = 0; nth < grid.n_tiles(); ++nth) {
      const int64_t tile = order[nth];
      const int64_t begin = offsets[tile], end = offsets[tile + 1];
      if (begin == end) continue;
      const TileRect r = grid.rect(tile);
      const int64_t tx0 = r.x0, ty0 = r.y0, tw = r.w, th = r.h;
      int32_t max_last = 0;
      for (int64_t y = 0; y < th; ++y) {
        for (int64_t x = 0; x < tw; ++x) {
          const int64_t p = y * t + x, pix = (ty0 + y) * grid.width + (tx0 + x);
          double dot_bg = 0.0;
          for (int ch = 0; ch < 3; ++ch) {
            g[3 * p + ch] = static_cast<double>(grad_rgb[3 * pix + ch]);
            dot_bg += g[3 * p + ch] * background[ch];
          }
          trans[p] = t_final[pix];
          // T_final times d loss / d T_final (rgb gains T_final * background, alpha = 1 - T_final)
          behind[p] = t_final[pix] * (dot_bg - static_cast<double>(grad_alpha[pix]));
          last[p] = last_in[pix];
          max_last = std::max(max_last, last[p]);
        }
      }
      zero_entries(entry_grads, slots, begin + max_last, end);
      for (int64_t k = begin + max_last - 1; k >= begin; --k) {
        const Splat<scalar_t>& s = splats[ids[k]];
        const int64_t x0 = std::max<int64_t>(s.x0, tx0), x1 = std::min<int64_t>(s.x1, tx0 + tw - 1);
        const int64_t y0 = std::max<int64_t>(s.y0, ty0), y1 = std::min<int64_t>(s.y1, ty0 + th - 1);
        const int32_t position = static_cast<int32_t>(k - begin);
        double gm_x = 0, gm_y = 0, gc_a = 0, gc_b = 0, gc_c = 0, g_op = 0, gr = 0, gg = 0, gb = 0;
        const double a = s.a, b = s.b, c = s.c;
        for (int64_t y = y0; y <= y1; ++y) {
          const scalar_t dy = s.my - (static_cast<scalar_t>(y) + scalar_t(0.5));
          for (int64_t x = x0; x <= x1; ++x) {
            const int64_t p = (y - ty0) * t + (x - tx0);
            if (position >= last[p]) continue;
            const scalar_t dx = s.mx - (static_cast<scalar_t>(x) + scalar_t(0.5));
            const scalar_t sigma = scalar_t(0.5) * (s.a * dx * dx + s.c * dy * dy) + s.b * dx * dy;
            if (sigma > s.sigma_cut) continue;
            const scalar_t alpha_raw = s.opacity * std::exp(-sigma);
            if (alpha_raw < static_cast<scalar_t>(kAlphaMin)) continue;
            const double alpha = std::min(static_cast<double>(alpha_raw), kAlphaMax);
            const double keep = 1.0 - alpha;
            const double t_before = trans[p] / keep;
            trans[p] = t_before;
            const double gr_p = g[3 * p], gg_p = g[3 * p + 1], gb_p = g[3 * p + 2];
            const double color_dot = gr_p * s.r + gg_p * s.g + gb_p * s.bl;
            const double grad_alpha_pair = t_before * color_dot - behind[p] / keep;
            const double w = alpha * t_before;
            behind[p] += color_dot * w;
            gr += w * gr_p;
            gg += w * gg_p;
            gb += w * gb_p;
            if (alpha < kAlphaMax) {  // a capped alpha does not depend on sigma or opacity
              const double g_sigma = -alpha * grad_alpha_pair;
              const double ddx = dx, ddy = dy;
              gm_x += g_sigma * (a * ddx + b * ddy);
              gm_y += g_sigma * (b * ddx + c * ddy);
              gc_a += 0.5 * g_sigma * ddx * ddx;
              gc_b += g_sigma * ddx * ddy;
              gc_c += 0.5 * g_sigma * ddy * ddy;
              g_op += alpha / static_cast<double>(s.opacity) * grad_alpha_pair;
            }
          }
        }
        double* out = entry_grads + kEntryGrads * static_cast<int64_t>(slots[k]);
        out[0] = gm_x, out[1] = gm_y, out[2] = gc_a, out[3] = gc_b, out[4] = gc_c, out[5] = g_op;
        out[6] = gr, out[7] = gg, out[8] = gb;
      }
    }
  }
}


// ----------------------------------------------------------------------------- float32 lanes
// For float32 inputs, forward and backward evaluate one Gaussian over W adjacent pixels of a tile row
// per step, written once with GCC/Clang vector types (Vec<W>) and compiled per instruction set:
// AVX-512 and AVX2 (target attributes, no -march: builds are shared across machines, the path is
// picked at run time) and the baseline ISA ("vector": NEON on aarch64, SSE2 on x86-64, where it is
// selectable so that the code ARM runs is tested). Per pixel these are the scalar kernel's expressions
// in its order with an inlined polynomial exp (exp_lanes) instead of libm's; per-pixel state (T, colour
// sums; the backward's running sums) is float32, one register per value. No FMA contraction
// (-ffp-contract=off), so every lane path computes the same alpha, image and T bit for bit, whatever W.
// A step covers only the part of a row where the Gaussian can reach alpha >= 1/255 (RowSpan: the
// ellipse sigma <= sigma_cut solved per row, widened for rounding), not its whole box, whose corners
// lie outside the ellipse: at 256^2 a box row is often 8-12 pixels and its span 3-6.

enum class Simd { kScalar, kVector, kAvx2, kAvx512 };

#define GEOAVATAR_INLINE inline __attribute__((always_inline))

constexpr float kAlphaMinF = static_cast<float>(kAlphaMin);
constexpr float kAlphaMaxF = static_cast<float>(kAlphaMax);
constexpr float kTransmittanceMinF = static_cast<float>(kTransmittanceMin);
// Lanes per step of the row kernel (forward, backward): one native register of floats. Wider vectors
// than the ISA's registers are split by the compiler, and GCC then selects lane by lane (measured:
// 16 lanes on AVX-512 in vector types ran slower than the scalar kernel; the x86 paths are written
// with intrinsics for that reason, "block lanes").
constexpr int kMaxLanes = 16;
#ifndef GEOAVATAR_LANES_VECTOR_FWD
#define GEOAVATAR_LANES_VECTOR_FWD 4   // 128-bit: NEON q, SSE2 xmm
#define GEOAVATAR_LANES_VECTOR_BWD 4
#endif

// Pixel rows of the tile planes on the lane paths: a step may start at any column of the tile, so
// rows are padded by kMaxLanes columns that its masked lanes can read and write back unchanged.
inline int64_t lane_stride(int64_t tile) { return tile + kMaxLanes; }

// Where pixel (y, x) of a tile lies in the lane kernels' scratch planes: rows of lane_stride(tile)
// (the generic kernel), or 4 x 4 blocks of 16 values, block rows of blocks_x blocks (the AVX-512 kernel:
// one zmm per block).
struct PlaneLayout {
  int64_t stride, blocks_x;  // blocks_x = 0: rows
  static PlaneLayout rows(int64_t tile) { return {lane_stride(tile), 0}; }
  static PlaneLayout blocks(int64_t tile) { return {0, (tile + 3) / 4}; }
  int64_t size(int64_t tile) const { return blocks_x ? 16 * blocks_x * blocks_x : tile * stride; }
  int64_t index(int64_t y, int64_t x) const {
    return blocks_x ? 16 * ((y >> 2) * blocks_x + (x >> 2)) + 4 * (y & 3) + (x & 3) : y * stride + x;
  }
};

// The columns of one pixel row where sigma <= cut can hold: sigma is a quadratic in dx = mx - (x + 0.5)
// (0.5 a dx^2 + b dy dx + 0.5 c dy^2), solved in double. cut is sigma_cut (already 1e-3 above where
// o exp(-sigma) = 1/255) plus 1e-3 for the float evaluation of sigma, and the span is widened by
// 0.01 px for the float rounding of dx (one ulp of a pixel coordinate, 5e-4 px at x = 4096); it is
// then cut to the box. A conic that is not positive definite (never from the projection) keeps the box.
struct RowSpan {
  double mx, a, b, c, cut;
  bool solve;
  explicit RowSpan(const Splat<float>& s)
      : mx(s.mx), a(s.a), b(s.b), c(s.c), cut(static_cast<double>(s.sigma_cut) + 1e-3) {
    solve = a > 0 && a * c - b * b > 0 && std::isfinite(cut) && std::isfinite(mx);
  }
  // [xa, xb] within the box columns [x0, x1] (image columns); false when the row has none.
  GEOAVATAR_INLINE bool columns(float dy, int64_t x0, int64_t x1, int64_t& xa, int64_t& xb) const {
    xa = x0, xb = x1;
    if (!solve) return true;
    if (cut < 0) return false;  // sigma >= 0 everywhere
    const double ddy = dy;
    const double disc = (b * b - a * c) * ddy * ddy + 2.0 * a * cut;
    if (disc < 0) return false;
    const double root = std::sqrt(disc), centre = -b * ddy;
    const double dx_lo = (centre - root) / a, dx_hi = (centre + root) / a;
    // x + 0.5 = mx - dx: columns from mx - dx_hi to mx - dx_lo
    const double lo = std::ceil(mx - dx_hi - 0.5 - 0.01), hi = std::floor(mx - dx_lo - 0.5 + 0.01);
    if (lo > static_cast<double>(xa)) xa = lo > static_cast<double>(x1) ? x1 + 1 : static_cast<int64_t>(lo);
    if (hi < static_cast<double>(xb)) xb = hi < static_cast<double>(x0) ? x0 - 1 : static_cast<int64_t>(hi);
    return xa <= xb;
  }
};

#if defined(__GNUC__)  // GCC and Clang vector extensions
#pragma GCC diagnostic ignored "-Wpsabi"  // vectors passed between always-inlined helpers only

// W lanes of float / int32 and of double / int64 (a comparison of F gives I, of D gives L).
template <int W>
struct Vec {
  typedef float F __attribute__((vector_size(4 * W)));
  typedef int32_t I __attribute__((vector_size(4 * W)));
  typedef double D __attribute__((vector_size(8 * W)));
  typedef int64_t L __attribute__((vector_size(8 * W)));
};

template <typename V, typename T>
GEOAVATAR_INLINE V splat(T value) {
  return V{} + value;  // a scalar operand is broadcast to every lane
}

template <typename V, typename T>
GEOAVATAR_INLINE V load(const T* p) {
  V v;
  std::memcpy(&v, p, sizeof v);
  return v;
}

template <typename V, typename T>
GEOAVATAR_INLINE void store(T* p, const V& v) {
  std::memcpy(p, &v, sizeof v);
}

template <typename I>
GEOAVATAR_INLINE I lane_index() {
  I v;
  for (size_t l = 0; l < sizeof(I) / sizeof(v[0]); ++l) v[l] = static_cast<int32_t>(l);
  return v;
}

// exp(x) per lane without a libm call: Cephes' expf (x = n ln 2 + r with ln 2 in two parts, a degree-6
// polynomial in r), within 2 ulp of expf. x is clamped to [-80, 88]: o exp(x) is then far below 1/255
// or capped at 0.999 anyway, and results stay clear of denormals (each costs a microcode assist, and
// masked lanes may lie far outside the ellipse).
template <typename F, typename I>
GEOAVATAR_INLINE F exp_lanes(F x) {
  const F lo = splat<F>(-80.0f), hi = splat<F>(88.0f);
  x = x < lo ? lo : x;  // std::max(x, -80), then std::min(x, 88)
  x = hi < x ? hi : x;
  const F round = splat<F>(12582912.0f);  // 1.5 * 2^23: adding it rounds to an integer
  const F n = (x * splat<F>(1.44269504088896341f) + round) - round;
  const F r = (x - n * splat<F>(0.693359375f)) - n * splat<F>(-2.12194440e-4f);
  F p = splat<F>(1.9875691500e-4f);
  p = p * r + splat<F>(1.3981999507e-3f);
  p = p * r + splat<F>(8.3334519073e-3f);
  p = p * r + splat<F>(4.1665795894e-2f);
  p = p * r + splat<F>(1.6666665459e-1f);
  p = p * r + splat<F>(5.0000001201e-1f);
  p = p * r * r + r + splat<F>(1.0f);
  const I bits = (__builtin_convertvector(n, I) + 127) << 23;  // 2^n
  return p * reinterpret_cast<const F&>(bits);
}

// Sum of a vector's lanes, by halves: vector adds, not one extraction per lane, in a fixed order (a
// shuffle-free tree), so an entry's gradient depends on nothing but its pixels. Any lane type and width.
template <typename V>
GEOAVATAR_INLINE auto sum_lanes(V v) {
  using T = std::remove_cv_t<std::remove_reference_t<decltype(v[0])>>;
  if constexpr (sizeof(V) == 2 * sizeof(T)) {
    return v[0] + v[1];
  } else {
    typedef T Half __attribute__((vector_size(sizeof(V) / 2)));
    Half lo, hi;
    std::memcpy(&lo, &v, sizeof lo);
    std::memcpy(&hi, reinterpret_cast<const char*>(&v) + sizeof lo, sizeof hi);
    return sum_lanes(lo + hi);
  }
}
#endif

// A tile's entries are in depth order and their splats lie scattered in memory (a Splat<float> spans two
// cache lines): the lane loops fetch the splat of the entry kPrefetch ahead while working on this one.
constexpr int64_t kPrefetch = 4;

template <typename T>
GEOAVATAR_INLINE void prefetch_splat(const T* splat) {
  __builtin_prefetch(splat);
  __builtin_prefetch(reinterpret_cast<const char*>(splat) + 64);
}

// One tile of the lane forward: geometry, its entries and per-thread scratch planes (PlaneLayout).
struct LaneTile {
  const Splat<float>* splats;
  const int32_t* ids;
  int64_t begin, end, tx0, ty0, tw, th, stride, blocks_x;
  float *trans, *red, *green, *blue;
  int32_t *last, *done, *row_done;
};

#if defined(__GNUC__)
template <int W>
GEOAVATAR_INLINE void composite_tile_vec(const LaneTile& tile) {
  using F = typename Vec<W>::F;
  using I = typename Vec<W>::I;
  float* __restrict__ trans = tile.trans;
  float* __restrict__ red = tile.red;
  float* __restrict__ green = tile.green;
  float* __restrict__ blue = tile.blue;
  int32_t* __restrict__ last = tile.last;
  int32_t* __restrict__ done = tile.done;
  const int64_t tx0 = tile.tx0, ty0 = tile.ty0, tw = tile.tw, th = tile.th;
  const I zero_i = splat<I>(0), one_i = splat<I>(1);
  const F lane_f = __builtin_convertvector(lane_index<I>(), F);
  const F half = splat<F>(0.5f), one = splat<F>(1.0f), alpha_min = splat<F>(kAlphaMinF);
  const F alpha_max = splat<F>(kAlphaMaxF), t_min = splat<F>(kTransmittanceMinF);
  int64_t n_done = 0;
  for (int64_t k = tile.begin; k < tile.end && n_done < tw * th; ++k) {
    if (k + kPrefetch < tile.end) prefetch_splat(tile.splats + tile.ids[k + kPrefetch]);
    const Splat<float>& s = tile.splats[tile.ids[k]];
    const int64_t x0 = std::max<int64_t>(s.x0, tx0), x1 = std::min<int64_t>(s.x1, tx0 + tw - 1);
    const int64_t y0 = std::max<int64_t>(s.y0, ty0), y1 = std::min<int64_t>(s.y1, ty0 + th - 1);
    const I position = splat<I>(static_cast<int32_t>(k - tile.begin + 1));
    const RowSpan span(s);
    // A box row that one step covers is stepped whole (its lanes outside the span fail the alpha test
    // anyway): solving the span (sqrt, division, rounding in double) would cost more than it saves.
    const bool narrow = x1 - x0 < W;
    const F mx = splat<F>(s.mx), a = splat<F>(s.a), b = splat<F>(s.b), opacity = splat<F>(s.opacity);
    const F r = splat<F>(s.r), g = splat<F>(s.g), bl = splat<F>(s.bl);
    for (int64_t y = y0; y <= y1; ++y) {
      const int64_t row = y - ty0;
      if (tile.row_done[row] == tw) continue;
      const float dy = s.my - (static_cast<float>(y) + 0.5f);
      int64_t xa = x0, xb = x1;
      if (!narrow && !span.columns(dy, x0, x1, xa, xb)) continue;
      const F dy_v = splat<F>(dy), c_dy_dy = splat<F>(s.c * dy * dy);
      // pixel centres x + 0.5 of the lanes, and of the span's last column, in float: sums of small
      // integers and 0.5, exact, so dx is the scalar kernel's; the lanes past the span compare above
      // x_end (integer splats cost GCC a chain of inserts per step)
      F centre = lane_f + splat<F>(static_cast<float>(xa) + 0.5f);
      const F x_end = splat<F>(static_cast<float>(xb) + 0.5f);
      for (int64_t x = xa; x <= xb; x += W, centre += splat<F>(static_cast<float>(W))) {
        const int64_t base = row * tile.stride + (x - tx0);
        // the scalar kernel's expressions, in its order: the same float sigma bit for bit
        const F dx = mx - centre;
        const F sigma = half * (a * dx * dx + c_dy_dy) + b * dx * dy_v;
        const F alpha_raw = opacity * exp_lanes<F, I>(-sigma);
        const I done_here = load<I>(done + base);
        const I accept = (centre <= x_end) & (done_here == zero_i) &
                         (alpha_raw >= alpha_min);
        const F alpha = alpha_raw < alpha_max ? alpha_raw : alpha_max;
        const F t_here = load<F>(trans + base);
        const F next_t = t_here * (one - alpha);
        const I stop = accept & (next_t <= t_min);
        const I add = accept & ~stop;
        const F w = alpha * t_here;
        const F red_here = load<F>(red + base), green_here = load<F>(green + base), blue_here = load<F>(blue + base);
        store(red + base, add ? red_here + w * r : red_here);
        store(green + base, add ? green_here + w * g : green_here);
        store(blue + base, add ? blue_here + w * bl : blue_here);
        store(trans + base, add ? next_t : t_here);
        store(last + base, add ? position : load<I>(last + base));
        store(done + base, stop ? one_i : done_here);
        const int32_t stopped = -sum_lanes(stop);  // -1 per stopped lane
        tile.row_done[row] += stopped;
        n_done += stopped;
      }
    }
  }
}

// Compiled for the baseline ISA of the build (SSE2 on x86-64, NEON on aarch64).
void composite_tile_vector(const LaneTile& tile) { composite_tile_vec<GEOAVATAR_LANES_VECTOR_FWD>(tile); }
#endif

#if defined(__GNUC__) && (defined(__x86_64__) || defined(__i386__))
#define GEOAVATAR_X86_DISPATCH 1
#define GEOAVATAR_TARGET_AVX512 __attribute__((target("avx512f,avx512dq,avx512vl,avx512bw,prefer-vector-width=512")))
#define GEOAVATAR_TARGET_AVX2 __attribute__((target("avx2,fma")))
// ----------------------------------------------------------------------------- block lanes (AVX-512, AVX2)
// The x86 paths with intrinsics: one step is a Gaussian over a 4 x 4 block of the tile (16 lanes), whose
// scratch planes are stored block by block (PlaneLayout::blocks). GCC 12 lowers comparisons and selects on
// 64-byte vector types lane by lane (a vcomiss and setae per lane), so the generic kernel above can only
// use one register of lanes per step, over a row span; with masks kept as bits a step covers a block.
// Against the generic kernel's row spans:
//   - a box within a tile is ~6 x 6 pixels at 256^2 / 100k Gaussians: it meets ~4.2 blocks on average,
//     where one step per row takes ~6 steps of 16 lanes and row spans of 8 lanes more (measured on
//     frame 0: 849k blocks, 1.22M rows);
//   - no row span is solved (a double sqrt and division per row), the alpha test masks the lanes
//     outside the ellipse, as it does for the scalar kernel's box pixels;
//   - every load of a plane reads what an earlier step stored at the same address and width (steps
//     starting at a box's first column overlapped earlier stores at other offsets, and such a load
//     waits for the store to retire: failed store-to-load forwarding);
//   - the forward's per-pixel "done" flags are one bit mask per block; a step with no lane left
//     skips exp, and one with no accepted lane the loads, stores and gradient terms.
// Per lane the arithmetic is the generic kernel's, in its order (same alpha, T and colour sums: images
// bit for bit); the backward's per-lane partial sums hold other pixels (gradients within the lane-path
// tolerances).
//
// One kernel source for both ISAs: the kernels are templates over a Lanes type (Avx512Lanes: one zmm and a
// k-register mask per block; Avx2Lanes: two ymm, rows 0-1 and 2-3, and the same 16-bit masks), written
// with the vector operators (no contraction: -ffp-contract=off). Only the lane operations carry a target
// ISA; each entry point (composite_tile_avx512, ...) has its target and `flatten`, which inlines the
// template and its lane operations into it, so each ISA's instructions stay in its own functions.
#define GEOAVATAR_LANE_OP GEOAVATAR_TARGET_AVX512 static inline
struct Avx512Lanes {
  using F = __m512;
  using I = __m512i;
  using M = __mmask16;
  using D = __m512d;
  GEOAVATAR_LANE_OP F splat(float v) { return _mm512_set1_ps(v); }
  GEOAVATAR_LANE_OP I splat_i(int32_t v) { return _mm512_set1_epi32(v); }
  GEOAVATAR_LANE_OP F load(const float* p) { return _mm512_loadu_ps(p); }
  GEOAVATAR_LANE_OP I load_i(const int32_t* p) { return _mm512_loadu_si512(p); }
  GEOAVATAR_LANE_OP void store(float* p, F v) { _mm512_storeu_ps(p, v); }
  GEOAVATAR_LANE_OP void store_i(int32_t* p, M m, I v) { _mm512_mask_storeu_epi32(p, m, v); }
  GEOAVATAR_LANE_OP M lt(M m, F a, F b) { return _mm512_mask_cmp_ps_mask(m, a, b, _CMP_LT_OQ); }
  GEOAVATAR_LANE_OP M le(M m, F a, F b) { return _mm512_mask_cmp_ps_mask(m, a, b, _CMP_LE_OQ); }
  GEOAVATAR_LANE_OP M ge(M m, F a, F b) { return _mm512_mask_cmp_ps_mask(m, a, b, _CMP_GE_OQ); }
  GEOAVATAR_LANE_OP M lt_i(M m, I a, I b) { return _mm512_mask_cmplt_epi32_mask(m, a, b); }
  // a < b ? a : b and a > b ? a : b (NaN: b), as the generic kernel's selects
  GEOAVATAR_LANE_OP F min(F a, F b) { return _mm512_min_ps(a, b); }
  GEOAVATAR_LANE_OP F max(F a, F b) { return _mm512_max_ps(a, b); }
  GEOAVATAR_LANE_OP F select(M m, F if_set, F if_not) { return _mm512_mask_mov_ps(if_not, m, if_set); }
  GEOAVATAR_LANE_OP F add_where(M m, F sum, F term) { return _mm512_mask_add_ps(sum, m, sum, term); }
  GEOAVATAR_LANE_OP F pow2(F n) {  // 2^n for integral n in [-127, 127]: the exponent bits
    return _mm512_castsi512_ps(_mm512_slli_epi32(_mm512_add_epi32(_mm512_cvttps_epi32(n), _mm512_set1_epi32(127)), 23));
  }
  // column and row of each lane within its 4 x 4 block
  GEOAVATAR_LANE_OP F lane_x() { return _mm512_setr_ps(0, 1, 2, 3, 0, 1, 2, 3, 0, 1, 2, 3, 0, 1, 2, 3); }
  GEOAVATAR_LANE_OP F lane_y() { return _mm512_setr_ps(0, 0, 0, 0, 1, 1, 1, 1, 2, 2, 2, 2, 3, 3, 3, 3); }
  // lanes l and l + 8 first, then by halves: the generic kernel's order for 16 lanes
  GEOAVATAR_LANE_OP double sum(F v) {
    const D s8 = _mm512_cvtps_pd(_mm512_castps512_ps256(v)) + _mm512_cvtps_pd(_mm512_extractf32x8_ps(v, 1));
    const __m256d s4 = _mm512_castpd512_pd256(s8) + _mm512_extractf64x4_pd(s8, 1);
    const __m128d s2 = _mm256_castpd256_pd128(s4) + _mm256_extractf128_pd(s4, 1);
    return s2[0] + s2[1];
  }
#undef GEOAVATAR_LANE_OP
};

// The same 16 lanes on AVX2: two ymm registers per value (lo: the block's rows 0-1, hi: rows 2-3), masks
// as 16-bit integers (a comparison's movemask), widened back to lanes where a select needs them. Against
// one ymm per half block, two steps a block (8-bit masks, 9 instead of 18 registers for the backward's
// sums): 1.36x against 1.26-1.30x the row kernel (d3's frame 0, 70k Gaussians, 256 px), the halves'
// loop and masks costing more than the spills.
struct Avx2Lanes {
  struct F {
    __m256 lo, hi;
  };
  struct I {
    __m256i lo, hi;
  };
  using M = __mmask16;
#define GEOAVATAR_LANE_OP GEOAVATAR_TARGET_AVX2 static inline
  GEOAVATAR_LANE_OP F splat(float v) { return {_mm256_set1_ps(v), _mm256_set1_ps(v)}; }
  GEOAVATAR_LANE_OP I splat_i(int32_t v) { return {_mm256_set1_epi32(v), _mm256_set1_epi32(v)}; }
  GEOAVATAR_LANE_OP F load(const float* p) { return {_mm256_loadu_ps(p), _mm256_loadu_ps(p + 8)}; }
  GEOAVATAR_LANE_OP I load_i(const int32_t* p) {
    return {_mm256_loadu_si256(reinterpret_cast<const __m256i*>(p)),
            _mm256_loadu_si256(reinterpret_cast<const __m256i*>(p + 8))};
  }
  GEOAVATAR_LANE_OP void store(float* p, F v) {
    _mm256_storeu_ps(p, v.lo);
    _mm256_storeu_ps(p + 8, v.hi);
  }
  // the lanes of a 16-bit mask as all-ones / all-zeros lanes: bit l of m in lane l
  GEOAVATAR_LANE_OP __m256i lanes_lo(M m) {
    const __m256i bit = _mm256_setr_epi32(1, 2, 4, 8, 16, 32, 64, 128);
    return _mm256_cmpeq_epi32(_mm256_and_si256(_mm256_set1_epi32(m), bit), bit);
  }
  GEOAVATAR_LANE_OP __m256i lanes_hi(M m) { return lanes_lo(static_cast<M>(m >> 8)); }
  GEOAVATAR_LANE_OP M bits(__m256 lo, __m256 hi) {
    return static_cast<M>(_mm256_movemask_ps(lo) | _mm256_movemask_ps(hi) << 8);
  }
  // masked stores as load, blend, store: the planes are the calling thread's own scratch
  GEOAVATAR_LANE_OP void store_i(int32_t* p, M m, I v) {
    const I old = load_i(p);
    _mm256_storeu_si256(reinterpret_cast<__m256i*>(p),
                        _mm256_blendv_epi8(old.lo, v.lo, lanes_lo(m)));
    _mm256_storeu_si256(reinterpret_cast<__m256i*>(p + 8),
                        _mm256_blendv_epi8(old.hi, v.hi, lanes_hi(m)));
  }
  GEOAVATAR_LANE_OP M lt(M m, F a, F b) {
    return m & bits(_mm256_cmp_ps(a.lo, b.lo, _CMP_LT_OQ), _mm256_cmp_ps(a.hi, b.hi, _CMP_LT_OQ));
  }
  GEOAVATAR_LANE_OP M le(M m, F a, F b) {
    return m & bits(_mm256_cmp_ps(a.lo, b.lo, _CMP_LE_OQ), _mm256_cmp_ps(a.hi, b.hi, _CMP_LE_OQ));
  }
  GEOAVATAR_LANE_OP M ge(M m, F a, F b) {
    return m & bits(_mm256_cmp_ps(a.lo, b.lo, _CMP_GE_OQ), _mm256_cmp_ps(a.hi, b.hi, _CMP_GE_OQ));
  }
  GEOAVATAR_LANE_OP M lt_i(M m, I a, I b) {
    return m & bits(_mm256_castsi256_ps(_mm256_cmpgt_epi32(b.lo, a.lo)),
                    _mm256_castsi256_ps(_mm256_cmpgt_epi32(b.hi, a.hi)));
  }
  GEOAVATAR_LANE_OP F min(F a, F b) { return {_mm256_min_ps(a.lo, b.lo), _mm256_min_ps(a.hi, b.hi)}; }
  GEOAVATAR_LANE_OP F max(F a, F b) { return {_mm256_max_ps(a.lo, b.lo), _mm256_max_ps(a.hi, b.hi)}; }
  GEOAVATAR_LANE_OP F select(M m, F if_set, F if_not) {
    return {_mm256_blendv_ps(if_not.lo, if_set.lo, _mm256_castsi256_ps(lanes_lo(m))),
            _mm256_blendv_ps(if_not.hi, if_set.hi, _mm256_castsi256_ps(lanes_hi(m)))};
  }
  GEOAVATAR_LANE_OP F add_where(M m, F sum, F term) {
    return select(m, {sum.lo + term.lo, sum.hi + term.hi}, sum);
  }
  GEOAVATAR_LANE_OP F pow2(F n) {
    const __m256i bias = _mm256_set1_epi32(127);
    return {_mm256_castsi256_ps(_mm256_slli_epi32(_mm256_add_epi32(_mm256_cvttps_epi32(n.lo), bias), 23)),
            _mm256_castsi256_ps(_mm256_slli_epi32(_mm256_add_epi32(_mm256_cvttps_epi32(n.hi), bias), 23))};
  }
  GEOAVATAR_LANE_OP F lane_x() {
    const __m256 x = _mm256_setr_ps(0, 1, 2, 3, 0, 1, 2, 3);
    return {x, x};
  }
  GEOAVATAR_LANE_OP F lane_y() {
    return {_mm256_setr_ps(0, 0, 0, 0, 1, 1, 1, 1), _mm256_setr_ps(2, 2, 2, 2, 3, 3, 3, 3)};
  }
  // Avx512Lanes::sum's order: lanes l and l + 8 (lo and hi), then l and l + 4, ...
  GEOAVATAR_LANE_OP double sum(F v) {
    const __m256d first =
        _mm256_cvtps_pd(_mm256_castps256_ps128(v.lo)) + _mm256_cvtps_pd(_mm256_castps256_ps128(v.hi));
    const __m256d second =
        _mm256_cvtps_pd(_mm256_extractf128_ps(v.lo, 1)) + _mm256_cvtps_pd(_mm256_extractf128_ps(v.hi, 1));
    const __m256d s4 = first + second;
    const __m128d s2 = _mm256_castpd256_pd128(s4) + _mm256_extractf128_pd(s4, 1);
    return s2[0] + s2[1];
  }
#undef GEOAVATAR_LANE_OP
};

// Avx2Lanes' arithmetic, lane by lane on both halves.
#define GEOAVATAR_AVX2_BINARY(OP)                                                                        \
  GEOAVATAR_TARGET_AVX2 inline Avx2Lanes::F operator OP(Avx2Lanes::F a, Avx2Lanes::F b) {                 \
    return {a.lo OP b.lo, a.hi OP b.hi};                                                                  \
  }
GEOAVATAR_AVX2_BINARY(+)
GEOAVATAR_AVX2_BINARY(-)
GEOAVATAR_AVX2_BINARY(*)
GEOAVATAR_AVX2_BINARY(/)
#undef GEOAVATAR_AVX2_BINARY
GEOAVATAR_TARGET_AVX2 inline Avx2Lanes::F operator-(Avx2Lanes::F a) { return {-a.lo, -a.hi}; }

// exp_lanes with max / min for its clamps (the same values, NaN included).
template <typename L>
inline typename L::F exp_block(typename L::F x) {
  using F = typename L::F;
  x = L::max(L::splat(-80.0f), x);  // -80 > x ? -80 : x
  x = L::min(L::splat(88.0f), x);   // 88 < x ? 88 : x
  const F round = L::splat(12582912.0f);
  const F n = (x * L::splat(1.44269504088896341f) + round) - round;
  const F r = (x - n * L::splat(0.693359375f)) - n * L::splat(-2.12194440e-4f);
  F p = L::splat(1.9875691500e-4f);
  p = p * r + L::splat(1.3981999507e-3f);
  p = p * r + L::splat(8.3334519073e-3f);
  p = p * r + L::splat(4.1665795894e-2f);
  p = p * r + L::splat(1.6666665459e-1f);
  p = p * r + L::splat(5.0000001201e-1f);
  p = p * r * r + r + L::splat(1.0f);
  return p * L::pow2(n);
}

// Bits first .. last (clipped to 0 .. 3) of a 4-bit mask: the block's columns (or rows) in [lo, hi].
GEOAVATAR_INLINE uint32_t bits4(int64_t lo, int64_t hi) {
  const int64_t first = std::max<int64_t>(lo, 0), last = std::min<int64_t>(hi, 3);
  return first > last ? 0u : ((2u << last) - 1u) & ~((1u << first) - 1u);
}

// Lanes of a block whose row is in `rows` and column in `cols` (4-bit masks; lane = 4 row + column).
GEOAVATAR_INLINE uint32_t block_lanes(uint32_t rows, uint32_t cols) {
  const uint32_t spread = (rows & 1u) | (rows & 2u) << 3 | (rows & 4u) << 6 | (rows & 8u) << 9;
  return spread * cols;  // one copy of cols per row: no carries
}

// Blocks of one entry's box (tile coordinates), front of the loops of both kernels.
struct BlockBox {
  int64_t x0, x1, y0, y1;  // box within the tile, inclusive
  GEOAVATAR_INLINE BlockBox(const Splat<float>& s, int64_t tx0, int64_t ty0, int64_t tw, int64_t th)
      : x0(std::max<int64_t>(s.x0 - tx0, 0)), x1(std::min<int64_t>(s.x1 - tx0, tw - 1)),
        y0(std::max<int64_t>(s.y0 - ty0, 0)), y1(std::min<int64_t>(s.y1 - ty0, th - 1)) {}
};

// One Gaussian broadcast to the lanes, and what both kernels compute of it per block: the lanes' offsets
// dy, dx from the pixel centres y + 0.5, x + 0.5 (sums of small integers and 0.5, exact: the scalar
// kernel's), and o exp(-sigma) with the scalar kernel's expressions in its order (the same float sigma).
template <typename L>
struct BlockSplat {
  using F = typename L::F;
  F mx, my, a, b, c, opacity;
  inline explicit BlockSplat(const Splat<float>& s)
      : mx(L::splat(s.mx)), my(L::splat(s.my)), a(L::splat(s.a)), b(L::splat(s.b)), c(L::splat(s.c)),
        opacity(L::splat(s.opacity)) {}
  // y, x: image row / column of the block's first pixel
  inline F dy(int64_t y) const { return my - (L::lane_y() + L::splat(static_cast<float>(y) + 0.5f)); }
  inline F dx(int64_t x) const { return mx - (L::lane_x() + L::splat(static_cast<float>(x) + 0.5f)); }
  inline F alpha_raw(F dx, F dy, F c_dy_dy) const {
    const F sigma = L::splat(0.5f) * (a * dx * dx + c_dy_dy) + b * dx * dy;
    return opacity * exp_block<L>(-sigma);
  }
};

template <typename L>
inline void composite_tile_blocks(const LaneTile& tile) {
  using F = typename L::F;
  using M = typename L::M;
  float* __restrict__ trans = tile.trans;
  float* __restrict__ red = tile.red;
  float* __restrict__ green = tile.green;
  float* __restrict__ blue = tile.blue;
  int32_t* __restrict__ last = tile.last;
  // done pixels: one bit mask per block, in the caller's zeroed done plane
  uint32_t* __restrict__ done = reinterpret_cast<uint32_t*>(tile.done);
  const int64_t tx0 = tile.tx0, ty0 = tile.ty0, tw = tile.tw, th = tile.th, blocks_x = tile.blocks_x;
  const F one = L::splat(1.0f), alpha_min = L::splat(kAlphaMinF);
  const F alpha_max = L::splat(kAlphaMaxF), t_min = L::splat(kTransmittanceMinF);
  int64_t n_done = 0;
  for (int64_t k = tile.begin; k < tile.end && n_done < tw * th; ++k) {
    if (k + kPrefetch < tile.end) prefetch_splat(tile.splats + tile.ids[k + kPrefetch]);
    const Splat<float>& s = tile.splats[tile.ids[k]];
    const BlockBox box(s, tx0, ty0, tw, th);
    const auto position = L::splat_i(static_cast<int32_t>(k - tile.begin + 1));
    const BlockSplat<L> gauss(s);
    const F r = L::splat(s.r), g = L::splat(s.g), bl = L::splat(s.bl);
    for (int64_t by = box.y0 >> 2; by <= box.y1 >> 2; ++by) {
      const uint32_t rows = bits4(box.y0 - 4 * by, box.y1 - 4 * by);
      const F dy = gauss.dy(ty0 + 4 * by);
      const F c_dy_dy = gauss.c * dy * dy;
      for (int64_t bx = box.x0 >> 2; bx <= box.x1 >> 2; ++bx) {
        const int64_t block = by * blocks_x + bx, base = 16 * block;
        const M open = static_cast<M>(block_lanes(rows, bits4(box.x0 - 4 * bx, box.x1 - 4 * bx)) & ~done[block]);
        if (!open) continue;
        const F alpha_raw = gauss.alpha_raw(gauss.dx(tx0 + 4 * bx), dy, c_dy_dy);
        const M accept = L::ge(open, alpha_raw, alpha_min);
        if (!accept) continue;
        const F alpha = L::min(alpha_raw, alpha_max);
        const F t_here = L::load(trans + base);
        const F next_t = t_here * (one - alpha);
        const M stop = L::le(accept, next_t, t_min);
        const M add = accept & ~stop;
        const F w = alpha * t_here;
        L::store(red + base, L::add_where(add, L::load(red + base), w * r));
        L::store(green + base, L::add_where(add, L::load(green + base), w * g));
        L::store(blue + base, L::add_where(add, L::load(blue + base), w * bl));
        L::store(trans + base, L::select(add, next_t, t_here));
        L::store_i(last + base, add, position);
        if (stop) {
          done[block] |= stop;
          n_done += __builtin_popcount(stop);
        }
      }
    }
  }
}

// flatten: the template and its lane operations are inlined here, under this function's ISA.
GEOAVATAR_TARGET_AVX512 __attribute__((flatten)) void composite_tile_avx512(const LaneTile& tile) {
  composite_tile_blocks<Avx512Lanes>(tile);
}
GEOAVATAR_TARGET_AVX2 __attribute__((flatten)) void composite_tile_avx2(const LaneTile& tile) {
  composite_tile_blocks<Avx2Lanes>(tile);
}
#endif

bool simd_supported(Simd simd) {
#ifdef GEOAVATAR_X86_DISPATCH
  __builtin_cpu_init();
  if (simd == Simd::kAvx512)
    return __builtin_cpu_supports("avx512f") && __builtin_cpu_supports("avx512dq") &&
           __builtin_cpu_supports("avx512vl") && __builtin_cpu_supports("avx512bw");
  if (simd == Simd::kAvx2) return __builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma");
#else
  if (simd == Simd::kAvx512 || simd == Simd::kAvx2) return false;
#endif
#if !defined(__GNUC__)
  if (simd == Simd::kVector) return false;
#endif
  return true;
}

// The paths that step over 4 x 4 blocks (their planes block by block), not row spans.
bool block_path(Simd simd) { return simd == Simd::kAvx512 || simd == Simd::kAvx2; }

// Fastest first; "auto" takes the first this CPU runs.
constexpr Simd kAllSimd[] = {Simd::kAvx512, Simd::kAvx2, Simd::kVector, Simd::kScalar};

const char* simd_name(Simd simd) {
  switch (simd) {
    case Simd::kAvx512: return "avx512";
    case Simd::kAvx2: return "avx2";
    case Simd::kVector: return "vector";
    default: return "scalar";
  }
}

// The float32 paths this CPU runs, fastest first: "avx512", "avx2", "vector" (the lane code on the
// build's baseline ISA), "scalar" (the per-pixel loop with libm's exp and double state: the kernel
// before the lane paths).
std::vector<std::string> simd_paths() {
  std::vector<std::string> names;
  for (Simd simd : kAllSimd)
    if (simd_supported(simd)) names.push_back(simd_name(simd));
  return names;
}

Simd parse_simd(const std::string& name) {
  for (Simd simd : kAllSimd) {
    if (name == simd_name(simd)) {
      TORCH_CHECK(simd_supported(simd), "rasterize_cpu: this CPU cannot run the '", name, "' path");
      return simd;
    }
  }
  TORCH_CHECK(false, "rasterize_cpu: unknown SIMD path '", name, "'");
}

void forward_tiles_lanes(const Splat<float>* splats, const std::vector<int64_t>& offsets,
                         const std::vector<int32_t>& ids, const double* background, const Grid& grid, Simd simd,
                         float* out_rgb, float* out_alpha, int32_t* out_last, double* out_t_final) {
  void (*composite)(const LaneTile&) = nullptr;
#if defined(__GNUC__)
  if (simd == Simd::kVector) composite = composite_tile_vector;
#endif
#ifdef GEOAVATAR_X86_DISPATCH
  if (simd == Simd::kAvx512) composite = composite_tile_avx512;
  if (simd == Simd::kAvx2) composite = composite_tile_avx2;
#endif
  TORCH_CHECK(composite != nullptr, "rasterize_cpu: no SIMD compositing on this CPU");
  const int64_t t = grid.tile;
  const PlaneLayout layout = block_path(simd) ? PlaneLayout::blocks(t) : PlaneLayout::rows(t);
  const int64_t plane = layout.size(t);
  const std::vector<int32_t> order = tiles_by_work(offsets.data(), grid.n_tiles());
#pragma omp parallel num_threads(threads_for_torch())
  {
    std::vector<float> trans(plane), red(plane), green(plane), blue(plane);
    std::vector<int32_t> last(plane), done(plane), row_done(t);
#pragma omp for schedule(dynamic, 1)
    for (int64_t nth = 0; nth < grid.n_tiles(); ++nth) {
      const int64_t tile = order[nth];
      const TileRect r = grid.rect(tile);
      const int64_t tx0 = r.x0, ty0 = r.y0, tw = r.w, th = r.h;
      std::fill(trans.begin(), trans.end(), 1.0f);
      std::fill(red.begin(), red.end(), 0.0f);
      std::fill(green.begin(), green.end(), 0.0f);
      std::fill(blue.begin(), blue.end(), 0.0f);
      std::fill(last.begin(), last.end(), 0);
      std::fill(done.begin(), done.end(), 0);
      std::fill(row_done.begin(), row_done.end(), 0);
      composite(LaneTile{splats, ids.data(), offsets[tile], offsets[tile + 1], tx0, ty0, tw, th, layout.stride,
                         layout.blocks_x,
                         trans.data(), red.data(), green.data(), blue.data(), last.data(), done.data(),
                         row_done.data()});
      for (int64_t y = 0; y < th; ++y) {
        for (int64_t x = 0; x < tw; ++x) {
          const int64_t p = layout.index(y, x), pix = (ty0 + y) * grid.width + (tx0 + x);
          out_rgb[3 * pix] = static_cast<float>(red[p] + trans[p] * background[0]);
          out_rgb[3 * pix + 1] = static_cast<float>(green[p] + trans[p] * background[1]);
          out_rgb[3 * pix + 2] = static_cast<float>(blue[p] + trans[p] * background[2]);
          out_alpha[pix] = static_cast<float>(1.0 - trans[p]);
          out_last[pix] = last[p];
          out_t_final[pix] = trans[p];
        }
      }
    }
  }
}

// float64 always composites on the scalar path (libm exp: gradcheck needs the accuracy).
template <typename scalar_t>
void forward_tiles(const Splat<scalar_t>* splats, const std::vector<int64_t>& offsets,
                   const std::vector<int32_t>& ids, const double* background, const Grid& grid, Simd,
                   scalar_t* out_rgb, scalar_t* out_alpha, int32_t* out_last, double* out_t_final) {
  forward_tiles_scalar<scalar_t>(splats, offsets, ids, background, grid, out_rgb, out_alpha, out_last, out_t_final);
}

void forward_tiles(const Splat<float>* splats, const std::vector<int64_t>& offsets,
                   const std::vector<int32_t>& ids, const double* background, const Grid& grid, Simd simd,
                   float* out_rgb, float* out_alpha, int32_t* out_last, double* out_t_final) {
  if (simd == Simd::kScalar)
    forward_tiles_scalar<float>(splats, offsets, ids, background, grid, out_rgb, out_alpha, out_last, out_t_final);
  else
    forward_tiles_lanes(splats, offsets, ids, background, grid, simd, out_rgb, out_alpha, out_last, out_t_final);
}

// Backward of the lane paths: back to front over the entries of a tile, one Gaussian over W pixels of
// a row span per step; alpha is the lane forward's, bit for bit. The running state (T recovered by
// division, what lies behind, d loss / d rgb) is float32 like the forward's, so a step is one register
// per value (double state needs two per value on AVX2 and measured no faster than the scalar kernel).
// Each gradient sum is kept per lane over the entry's pixels, then the lanes are added in double in a
// fixed order (halves: lanes l and l + W/2 first), so results do not depend on the thread count. Against the double-state backward this
// moves gradients by a few float ulps of their terms (tests: within the lane-vs-scalar tolerances).
struct LaneBackTile {
  const Splat<float>* splats;
  const int32_t *ids, *slots;
  int64_t begin, end, tx0, ty0, tw, th, stride, blocks_x;
  int32_t max_last;
  float *trans, *behind, *grad_r, *grad_g, *grad_b;
  const int32_t* last;
  double* entry_grads;
};

#if defined(__GNUC__)
template <int W>
GEOAVATAR_INLINE void backward_tile_vec(const LaneBackTile& tile) {
  using F = typename Vec<W>::F;
  using I = typename Vec<W>::I;
  using D = typename Vec<W>::D;
  float* __restrict__ trans = tile.trans;
  float* __restrict__ behind = tile.behind;
  const float* __restrict__ grad_r = tile.grad_r;
  const float* __restrict__ grad_g = tile.grad_g;
  const float* __restrict__ grad_b = tile.grad_b;
  const int32_t* __restrict__ last = tile.last;
  const int64_t tx0 = tile.tx0, ty0 = tile.ty0, tw = tile.tw, th = tile.th;
  const F lane_f = __builtin_convertvector(lane_index<I>(), F);
  const F zero = splat<F>(0.0f), one = splat<F>(1.0f), half = splat<F>(0.5f);
  const F alpha_min = splat<F>(kAlphaMinF), alpha_max = splat<F>(kAlphaMaxF);
  for (int64_t k = tile.begin + tile.max_last - 1; k >= tile.begin; --k) {
    if (k - kPrefetch >= tile.begin) prefetch_splat(tile.splats + tile.ids[k - kPrefetch]);
    const Splat<float>& s = tile.splats[tile.ids[k]];
    const int64_t x0 = std::max<int64_t>(s.x0, tx0), x1 = std::min<int64_t>(s.x1, tx0 + tw - 1);
    const int64_t y0 = std::max<int64_t>(s.y0, ty0), y1 = std::min<int64_t>(s.y1, ty0 + th - 1);
    const I position = splat<I>(static_cast<int32_t>(k - tile.begin));
    const RowSpan span(s);
    const bool narrow = x1 - x0 < W;  // as in the forward: one step covers the row
    const F mx = splat<F>(s.mx), a = splat<F>(s.a), b = splat<F>(s.b), c = splat<F>(s.c);
    const F opacity = splat<F>(s.opacity), inv_opacity = splat<F>(1.0f / s.opacity);
    const F red = splat<F>(s.r), green = splat<F>(s.g), blue = splat<F>(s.bl);
    F sums[kEntryGrads];
    for (F& sum : sums) sum = zero;
    for (int64_t y = y0; y <= y1; ++y) {
      const int64_t row = y - ty0;
      const float dy = s.my - (static_cast<float>(y) + 0.5f);
      int64_t xa = x0, xb = x1;
      if (!narrow && !span.columns(dy, x0, x1, xa, xb)) continue;
      const F dy_v = splat<F>(dy), c_dy_dy = splat<F>(s.c * dy * dy);
      F centre = lane_f + splat<F>(static_cast<float>(xa) + 0.5f);  // as in the forward
      const F x_end = splat<F>(static_cast<float>(xb) + 0.5f);
      for (int64_t x = xa; x <= xb; x += W, centre += splat<F>(static_cast<float>(W))) {
        const int64_t base = row * tile.stride + (x - tx0);
        // alpha exactly as the lane forward computed it
        const F dx = mx - centre;
        const F sigma = half * (a * dx * dx + c_dy_dy) + b * dx * dy_v;
        const F alpha_raw = opacity * exp_lanes<F, I>(-sigma);
        const I in = (centre <= x_end) & (position < load<I>(last + base)) &
                     (alpha_raw >= alpha_min);
        const I uncapped = in & (alpha_raw < alpha_max);  // a capped alpha depends on neither sigma nor opacity
        const F alpha = alpha_raw < alpha_max ? alpha_raw : alpha_max;  // the forward's float alpha
        const F keep = one - alpha;
        const F t_after = load<F>(trans + base), behind_here = load<F>(behind + base);
        const F t_before = t_after / keep;
        const F gr = load<F>(grad_r + base), gg = load<F>(grad_g + base), gb = load<F>(grad_b + base);
        const F color_dot = gr * red + gg * green + gb * blue;
        const F grad_alpha_pair = t_before * color_dot - behind_here / keep;
        const F w = alpha * t_before;
        store(trans + base, in ? t_before : t_after);
        store(behind + base, in ? behind_here + color_dot * w : behind_here);
        const F g_sigma = -alpha * grad_alpha_pair;
        sums[0] += uncapped ? g_sigma * (a * dx + b * dy_v) : zero;
        sums[1] += uncapped ? g_sigma * (b * dx + c * dy_v) : zero;
        sums[2] += uncapped ? half * g_sigma * dx * dx : zero;
        sums[3] += uncapped ? g_sigma * dx * dy_v : zero;
        sums[4] += uncapped ? half * g_sigma * dy_v * dy_v : zero;
        sums[5] += uncapped ? alpha * inv_opacity * grad_alpha_pair : zero;
        sums[6] += in ? w * gr : zero;
        sums[7] += in ? w * gg : zero;
        sums[8] += in ? w * gb : zero;
      }
    }
    double* out = tile.entry_grads + kEntryGrads * static_cast<int64_t>(tile.slots[k]);
    for (int j = 0; j < kEntryGrads; ++j) out[j] = sum_lanes(__builtin_convertvector(sums[j], D));
  }
}

void backward_tile_vector(const LaneBackTile& tile) { backward_tile_vec<GEOAVATAR_LANES_VECTOR_BWD>(tile); }
#endif

#ifdef GEOAVATAR_X86_DISPATCH
// The lane backward on the block paths: backward_tile_vec's arithmetic over the blocks of
// composite_tile_blocks.
template <typename L>
inline void backward_tile_blocks(const LaneBackTile& tile) {
  using F = typename L::F;
  using M = typename L::M;
  float* __restrict__ trans = tile.trans;
  float* __restrict__ behind = tile.behind;
  const float* __restrict__ grad_r = tile.grad_r;
  const float* __restrict__ grad_g = tile.grad_g;
  const float* __restrict__ grad_b = tile.grad_b;
  const int32_t* __restrict__ last = tile.last;
  const int64_t tx0 = tile.tx0, ty0 = tile.ty0, tw = tile.tw, th = tile.th, blocks_x = tile.blocks_x;
  const F zero = L::splat(0.0f), one = L::splat(1.0f), half = L::splat(0.5f);
  const F alpha_min = L::splat(kAlphaMinF), alpha_max = L::splat(kAlphaMaxF);
  for (int64_t k = tile.begin + tile.max_last - 1; k >= tile.begin; --k) {
    if (k - kPrefetch >= tile.begin) prefetch_splat(tile.splats + tile.ids[k - kPrefetch]);
    const Splat<float>& s = tile.splats[tile.ids[k]];
    const BlockBox box(s, tx0, ty0, tw, th);
    const auto position = L::splat_i(static_cast<int32_t>(k - tile.begin));
    const BlockSplat<L> gauss(s);
    const F a = gauss.a, b = gauss.b, c = gauss.c, inv_opacity = L::splat(1.0f / s.opacity);
    const F red = L::splat(s.r), green = L::splat(s.g), blue = L::splat(s.bl);
    F sums[kEntryGrads];
    for (F& sum : sums) sum = zero;
    for (int64_t by = box.y0 >> 2; by <= box.y1 >> 2; ++by) {
      const uint32_t rows = bits4(box.y0 - 4 * by, box.y1 - 4 * by);
      const F dy = gauss.dy(ty0 + 4 * by);
      const F c_dy_dy = c * dy * dy;
      for (int64_t bx = box.x0 >> 2; bx <= box.x1 >> 2; ++bx) {
        const int64_t base = 16 * (by * blocks_x + bx);
        // lanes of the box in front of the pixel's last composited entry
        const M open = L::lt_i(static_cast<M>(block_lanes(rows, bits4(box.x0 - 4 * bx, box.x1 - 4 * bx))),
                               position, L::load_i(last + base));
        if (!open) continue;
        const F dx = gauss.dx(tx0 + 4 * bx);
        const F alpha_raw = gauss.alpha_raw(dx, dy, c_dy_dy);  // exactly the forward's
        const M in = L::ge(open, alpha_raw, alpha_min);
        if (!in) continue;
        const M uncapped = L::lt(in, alpha_raw, alpha_max);  // a capped alpha depends on neither sigma nor opacity
        const F alpha = L::min(alpha_raw, alpha_max);
        const F keep = one - alpha;
        const F t_after = L::load(trans + base), behind_here = L::load(behind + base);
        const F t_before = t_after / keep;
        const F gr = L::load(grad_r + base), gg = L::load(grad_g + base), gb = L::load(grad_b + base);
        const F color_dot = gr * red + gg * green + gb * blue;
        const F grad_alpha_pair = t_before * color_dot - behind_here / keep;
        const F w = alpha * t_before;
        L::store(trans + base, L::select(in, t_before, t_after));
        L::store(behind + base, L::add_where(in, behind_here, color_dot * w));
        const F g_sigma = -alpha * grad_alpha_pair;
        sums[0] = L::add_where(uncapped, sums[0], g_sigma * (a * dx + b * dy));
        sums[1] = L::add_where(uncapped, sums[1], g_sigma * (b * dx + c * dy));
        sums[2] = L::add_where(uncapped, sums[2], half * g_sigma * dx * dx);
        sums[3] = L::add_where(uncapped, sums[3], g_sigma * dx * dy);
        sums[4] = L::add_where(uncapped, sums[4], half * g_sigma * dy * dy);
        sums[5] = L::add_where(uncapped, sums[5], alpha * inv_opacity * grad_alpha_pair);
        sums[6] = L::add_where(in, sums[6], w * gr);
        sums[7] = L::add_where(in, sums[7], w * gg);
        sums[8] = L::add_where(in, sums[8], w * gb);
      }
    }
    double* out = tile.entry_grads + kEntryGrads * static_cast<int64_t>(tile.slots[k]);
    for (int j = 0; j < kEntryGrads; ++j) out[j] = L::sum(sums[j]);
  }
}

GEOAVATAR_TARGET_AVX512 __attribute__((flatten)) void backward_tile_avx512(const LaneBackTile& tile) {
  backward_tile_blocks<Avx512Lanes>(tile);
}
GEOAVATAR_TARGET_AVX2 __attribute__((flatten)) void backward_tile_avx2(const LaneBackTile& tile) {
  backward_tile_blocks<Avx2Lanes>(tile);
}
#endif

void backward_tiles_lanes(const Splat<float>* splats, const int64_t* offsets, const int32_t* ids,
                          const int32_t* slots, const int32_t* last_in, const double* t_final,
                          const float* grad_rgb, const float* grad_alpha, const double* background,
                          const Grid& grid, Simd simd, double* entry_grads) {
  void (*backward_tile)(const LaneBackTile&) = nullptr;
#if defined(__GNUC__)
  if (simd == Simd::kVector) backward_tile = backward_tile_vector;
#endif
#ifdef GEOAVATAR_X86_DISPATCH
  if (simd == Simd::kAvx512) backward_tile = backward_tile_avx512;
  if (simd == Simd::kAvx2) backward_tile = backward_tile_avx2;
#endif
  TORCH_CHECK(backward_tile != nullptr, "rasterize_cpu: no SIMD backward on this CPU");
  const int64_t t = grid.tile;
  const PlaneLayout layout = block_path(simd) ? PlaneLayout::blocks(t) : PlaneLayout::rows(t);
  const int64_t plane = layout.size(t);
  const std::vector<int32_t> order = tiles_by_work(offsets, grid.n_tiles());
#pragma omp parallel num_threads(threads_for_torch())
  {
    // lanes outside a tile's pixels keep finite values (T = 1, zeros, or an earlier tile's): their
    // results are computed, then masked off
    std::vector<float> trans(plane, 1.0f), behind(plane, 0.0f), grad_r(plane, 0.0f), grad_g(plane, 0.0f),
        grad_b(plane, 0.0f);
    std::vector<int32_t> last(plane, 0);
#pragma omp for schedule(dynamic, 1)
    for (int64_t nth = 0; nth < grid.n_tiles(); ++nth) {
      const int64_t tile = order[nth];
      const int64_t begin = offsets[tile], end = offsets[tile + 1];
      if (begin == end) continue;
      const TileRect r = grid.rect(tile);
      const int64_t tx0 = r.x0, ty0 = r.y0, tw = r.w, th = r.h;
      int32_t max_last = 0;
      for (int64_t y = 0; y < th; ++y) {
        for (int64_t x = 0; x < tw; ++x) {
          const int64_t p = layout.index(y, x), pix = (ty0 + y) * grid.width + (tx0 + x);
          grad_r[p] = grad_rgb[3 * pix], grad_g[p] = grad_rgb[3 * pix + 1], grad_b[p] = grad_rgb[3 * pix + 2];
          const double dot_bg = static_cast<double>(grad_r[p]) * background[0] +
                                static_cast<double>(grad_g[p]) * background[1] +
                                static_cast<double>(grad_b[p]) * background[2];
          trans[p] = static_cast<float>(t_final[pix]);  // exact: the lane forward's float T
          // T_final times d loss / d T_final (rgb gains T_final * background, alpha = 1 - T_final)
          behind[p] = static_cast<float>(t_final[pix] * (dot_bg - static_cast<double>(grad_alpha[pix])));
          last[p] = last_in[pix];
          max_last = std::max(max_last, last[p]);
        }
      }
      zero_entries(entry_grads, slots, begin + max_last, end);
      backward_tile(LaneBackTile{splats, ids, slots, begin, end, tx0, ty0, tw, th, layout.stride, layout.blocks_x,
                                 max_last, trans.data(), behind.data(), grad_r.data(), grad_g.data(), grad_b.data(),
                                 last.data(), entry_grads});
    }
  }
}

template <typename scalar_t>
void backward_tiles_for(Simd, const Splat<scalar_t>* splats, const int64_t* offsets, const int32_t* ids,
                        const int32_t* slots, const int32_t* last, const double* t_final, const scalar_t* grad_rgb,
                        const scalar_t* grad_alpha, const double* background, const Grid& grid, double* entry_grads) {
  backward_tiles<scalar_t>(splats, offsets, ids, slots, last, t_final, grad_rgb, grad_alpha, background, grid,
                           entry_grads);
}

void backward_tiles_for(Simd simd, const Splat<float>* splats, const int64_t* offsets, const int32_t* ids,
                        const int32_t* slots, const int32_t* last, const double* t_final, const float* grad_rgb,
                        const float* grad_alpha, const double* background, const Grid& grid, double* entry_grads) {
  if (simd == Simd::kScalar)
    backward_tiles<float>(splats, offsets, ids, slots, last, t_final, grad_rgb, grad_alpha, background, grid,
                          entry_grads);
  else
    backward_tiles_lanes(splats, offsets, ids, slots, last, t_final, grad_rgb, grad_alpha, background, grid, simd,
                         entry_grads);
}

Grid make_grid(int64_t width, int64_t height, int64_t tile) {
  TORCH_CHECK(width > 0 && height > 0 && tile > 0, "rasterize_cpu: width, height and tile must be positive");
  return Grid{width, height, tile, (width + tile - 1) / tile, (height + tile - 1) / tile};
}

// Returns rgb [H, W, 3], alpha [H, W, 1] and the state backward needs: tile offsets [T + 1] int64,
// tile ids [M] int32, last [H, W] int32 (end of each pixel's composited range in its tile list),
// t_final [H, W] float64, the splat records (bytes), entry slots [M] int32 and firsts [N + 1] int64
// (see bin_gaussians).
std::vector<torch::Tensor> forward(const torch::Tensor& means2d, const torch::Tensor& conics,
                                   const torch::Tensor& opacities, const torch::Tensor& colors,
                                   const torch::Tensor& background, const torch::Tensor& radii,
                                   const torch::Tensor& depths, int64_t width, int64_t height, int64_t tile,
                                   const std::string& simd_name) {
  const auto dtype = means2d.scalar_type();
  const Simd simd = parse_simd(simd_name);
  check_input(means2d, "means2d", 2, dtype);
  check_input(conics, "conics", 2, dtype);
  check_input(opacities, "opacities", 1, dtype);
  check_input(colors, "colors", 2, dtype);
  check_input(background, "background", 1, dtype);
  check_input(radii, "radii", 2, torch::kInt32);
  check_input(depths, "depths", 1, dtype);
  const Grid grid = make_grid(width, height, tile);
  auto opts = means2d.options();
  torch::Tensor rgb = torch::empty({height, width, 3}, opts);
  torch::Tensor alpha = torch::empty({height, width, 1}, opts);
  torch::Tensor last = torch::empty({height, width}, opts.dtype(torch::kInt32));
  torch::Tensor t_final = torch::empty({height, width}, opts.dtype(torch::kFloat64));
  torch::Tensor offsets_t, ids_t, splats_t, slots_t;
  const int64_t n = means2d.size(0);
  torch::Tensor firsts_t = torch::empty({n + 1}, opts.dtype(torch::kInt64));
  const torch::Tensor bg64 = background.to(torch::kFloat64).contiguous();
  AT_DISPATCH_FLOATING_TYPES(dtype, "rasterize_cpu_forward", [&] {
    splats_t = torch::empty({n * static_cast<int64_t>(sizeof(Splat<scalar_t>))}, opts.dtype(torch::kUInt8));
    auto* splats = reinterpret_cast<Splat<scalar_t>*>(splats_t.data_ptr<uint8_t>());
    gather_splats<scalar_t>(means2d, conics, opacities, colors, radii, grid, splats);
    std::vector<int64_t> offsets;
    std::vector<int32_t> ids;
    slots_t = torch::empty({0}, opts.dtype(torch::kInt32));
    bin_gaussians<scalar_t>(splats, n, depths, grid, offsets, ids, slots_t, firsts_t.data_ptr<int64_t>());
    forward_tiles(splats, offsets, ids, bg64.data_ptr<double>(), grid, simd, rgb.data_ptr<scalar_t>(),
                  alpha.data_ptr<scalar_t>(), last.data_ptr<int32_t>(), t_final.data_ptr<double>());
    offsets_t = torch::from_blob(offsets.data(), {static_cast<int64_t>(offsets.size())}, torch::kInt64).clone();
    ids_t = torch::from_blob(ids.data(), {static_cast<int64_t>(ids.size())}, torch::kInt32).clone();
  });
  return {rgb, alpha, offsets_t, ids_t, last, t_final, splats_t, slots_t, firsts_t};
}

// Returns the gradients of means2d [N, 2], conics [N, 3], opacities [N], colors [N, 3].
std::vector<torch::Tensor> backward(const torch::Tensor& means2d, const torch::Tensor& conics,
                                    const torch::Tensor& opacities, const torch::Tensor& colors,
                                    const torch::Tensor& background, const torch::Tensor& splats_t,
                                    const torch::Tensor& offsets, const torch::Tensor& ids,
                                    const torch::Tensor& slots, const torch::Tensor& firsts,
                                    const torch::Tensor& last, const torch::Tensor& t_final,
                                    const torch::Tensor& grad_rgb, const torch::Tensor& grad_alpha, int64_t width,
                                    int64_t height, int64_t tile, const std::string& simd_name) {
  const auto dtype = means2d.scalar_type();
  const Simd simd = parse_simd(simd_name);  // the forward's path: the same exp
  check_input(means2d, "means2d", 2, dtype);
  check_input(conics, "conics", 2, dtype);
  check_input(opacities, "opacities", 1, dtype);
  check_input(colors, "colors", 2, dtype);
  check_input(background, "background", 1, dtype);
  check_input(splats_t, "splats", 1, torch::kUInt8);
  check_input(offsets, "offsets", 1, torch::kInt64);
  check_input(ids, "ids", 1, torch::kInt32);
  check_input(slots, "slots", 1, torch::kInt32);
  check_input(firsts, "firsts", 1, torch::kInt64);
  check_input(last, "last", 2, torch::kInt32);
  check_input(t_final, "t_final", 2, torch::kFloat64);
  check_input(grad_rgb, "grad_rgb", 3, dtype);
  check_input(grad_alpha, "grad_alpha", 3, dtype);
  const Grid grid = make_grid(width, height, tile);
  TORCH_CHECK(offsets.numel() == grid.n_tiles() + 1, "rasterize_cpu: 'offsets' does not match the tile grid");
  const int64_t n = means2d.size(0), m = ids.numel();
  TORCH_CHECK(slots.numel() == m && firsts.numel() == n + 1, "rasterize_cpu: 'slots' or 'firsts' do not match");
  auto opts = means2d.options();
  // every entry is written below: empty, not zeros
  torch::Tensor g_means2d = torch::empty({n, 2}, opts), g_conics = torch::empty({n, 3}, opts);
  torch::Tensor g_opacities = torch::empty({n}, opts), g_colors = torch::empty({n, 3}, opts);
  const torch::Tensor bg64 = background.to(torch::kFloat64).contiguous();
  AT_DISPATCH_FLOATING_TYPES(dtype, "rasterize_cpu_backward", [&] {
    TORCH_CHECK(splats_t.numel() == n * static_cast<int64_t>(sizeof(Splat<scalar_t>)),
                "rasterize_cpu: 'splats' does not match the Gaussians");
    const auto* splats = reinterpret_cast<const Splat<scalar_t>*>(splats_t.data_ptr<uint8_t>());
    std::unique_ptr<double[]> entry_grads(new double[static_cast<size_t>(kEntryGrads) * m]);
    backward_tiles_for(simd, splats, offsets.data_ptr<int64_t>(), ids.data_ptr<int32_t>(), slots.data_ptr<int32_t>(),
                       last.data_ptr<int32_t>(), t_final.data_ptr<double>(), grad_rgb.data_ptr<scalar_t>(),
                       grad_alpha.data_ptr<scalar_t>(), bg64.data_ptr<double>(), grid, entry_grads.get());
    // Sum the entries of each Gaussian in tile order (its slots): a fixed order, whatever the thread count.
    const double* e = entry_grads.get();
    const int64_t* first = firsts.data_ptr<int64_t>();
    scalar_t* gm = g_means2d.data_ptr<scalar_t>();
    scalar_t* gc = g_conics.data_ptr<scalar_t>();
    scalar_t* go = g_opacities.data_ptr<scalar_t>();
    scalar_t* gcol = g_colors.data_ptr<scalar_t>();
    parallel_over(n, [&](int64_t i) {
      double s[kEntryGrads] = {};
      for (int64_t k = first[i]; k < first[i + 1]; ++k)
        for (int j = 0; j < kEntryGrads; ++j) s[j] += e[kEntryGrads * k + j];
      gm[2 * i] = s[0], gm[2 * i + 1] = s[1];
      gc[3 * i] = s[2], gc[3 * i + 1] = s[3], gc[3 * i + 2] = s[4];
      go[i] = s[5];
      gcol[3 * i] = s[6], gcol[3 * i + 1] = s[7], gcol[3 * i + 2] = s[8];
    });
  });
  return {g_means2d, g_conics, g_opacities, g_colors};
}

// ----------------------------------------------------------------------------- projection
// EWA projection of one camera, the same rules and operation order as torch_backend.project_gaussians
// (near/far plane, Jacobian clamp at 1.3 x the half field of view, 0.3 px dilation, det > 0,
// opacity >= 1/255, opacity-aware radii, box overlapping the image). Computed in double.

constexpr double kNear = 0.01, kFar = 1e10, kEps2d = 0.3, kClampMargin = 0.3, kMaxExtent = 3.33;

struct Camera {
  double r[9], t[3], fx, fy, cx, cy, lim_x_pos, lim_x_neg, lim_y_pos, lim_y_neg;
  int64_t width, height;
};

template <typename scalar_t>
Camera make_camera(const scalar_t* view, const scalar_t* k, int64_t width, int64_t height) {
  Camera cam;
  for (int i = 0; i < 3; ++i) {
    for (int j = 0; j < 3; ++j) cam.r[3 * i + j] = view[4 * i + j];
    cam.t[i] = view[4 * i + 3];
  }
  cam.fx = k[0], cam.fy = k[4], cam.cx = k[2], cam.cy = k[5];
  cam.width = width, cam.height = height;
  cam.lim_x_pos = (width - cam.cx) / cam.fx + kClampMargin * 0.5 * width / cam.fx;
  cam.lim_x_neg = cam.cx / cam.fx + kClampMargin * 0.5 * width / cam.fx;
  cam.lim_y_pos = (height - cam.cy) / cam.fy + kClampMargin * 0.5 * height / cam.fy;
  cam.lim_y_neg = cam.cy / cam.fy + kClampMargin * 0.5 * height / cam.fy;
  return cam;
}

// Everything the backward pass needs about one Gaussian, recomputed from the inputs.
struct ProjectedGaussian {
  double n[4];         // normalised quaternion wxyz
  double qnorm;        // |q|
  double rq[9];        // rotation of the quaternion
  double mc[9];        // camera-space R_view R_q S (row-major)
  double x, y, z, iz;  // camera-space mean, 1 / z
  double tx, ty;       // clamped Jacobian point times z
  bool clamped_x, clamped_y;
  double j0[3], j1[3], u[3], v[3];
  double cov_a, cov_b, cov_c, det;
  bool in_range;
};

template <typename scalar_t>
void project_one(const Camera& cam, const scalar_t* mean, const scalar_t* quat, const scalar_t* scale,
                 ProjectedGaussian& g) {
  double m[3] = {mean[0], mean[1], mean[2]};
  double xc[3];
  for (int i = 0; i < 3; ++i) xc[i] = cam.r[3 * i] * m[0] + cam.r[3 * i + 1] * m[1] + cam.r[3 * i + 2] * m[2] + cam.t[i];
  g.x = xc[0], g.y = xc[1], g.z = xc[2];
  const double q0 = quat[0], q1 = quat[1], q2 = quat[2], q3 = quat[3];
  g.qnorm = std::sqrt(q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3);
  const double w = q0 / g.qnorm, x = q1 / g.qnorm, y = q2 / g.qnorm, z = q3 / g.qnorm;
  g.n[0] = w, g.n[1] = x, g.n[2] = y, g.n[3] = z;
  const double rq[9] = {1 - 2 * (y * y + z * z), 2 * (x * y - w * z),     2 * (x * z + w * y),
                        2 * (x * y + w * z),     1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
                        2 * (x * z - w * y),     2 * (y * z + w * x),     1 - 2 * (x * x + y * y)};
  double ms[9];
  for (int i = 0; i < 9; ++i) g.rq[i] = rq[i], ms[i] = rq[i] * static_cast<double>(scale[i % 3]);
  for (int i = 0; i < 3; ++i)
    for (int k = 0; k < 3; ++k)
      g.mc[3 * i + k] = cam.r[3 * i] * ms[k] + cam.r[3 * i + 1] * ms[3 + k] + cam.r[3 * i + 2] * ms[6 + k];
  g.in_range = g.z >= kNear && g.z <= kFar;
  const double zs = g.in_range ? g.z : 1.0;
  g.iz = 1.0 / zs;
  const double rx = g.x * g.iz, ry = g.y * g.iz;
  g.clamped_x = rx < -cam.lim_x_neg || rx > cam.lim_x_pos;
  g.clamped_y = ry < -cam.lim_y_neg || ry > cam.lim_y_pos;
  g.tx = zs * std::min(std::max(rx, -cam.lim_x_neg), cam.lim_x_pos);
  g.ty = zs * std::min(std::max(ry, -cam.lim_y_neg), cam.lim_y_pos);
  g.j0[0] = cam.fx * g.iz, g.j0[1] = 0, g.j0[2] = -cam.fx * g.tx * g.iz * g.iz;
  g.j1[0] = 0, g.j1[1] = cam.fy * g.iz, g.j1[2] = -cam.fy * g.ty * g.iz * g.iz;
  for (int k = 0; k < 3; ++k) {
    g.u[k] = g.j0[0] * g.mc[k] + g.j0[1] * g.mc[3 + k] + g.j0[2] * g.mc[6 + k];
    g.v[k] = g.j1[0] * g.mc[k] + g.j1[1] * g.mc[3 + k] + g.j1[2] * g.mc[6 + k];
  }
  g.cov_a = g.u[0] * g.u[0] + g.u[1] * g.u[1] + g.u[2] * g.u[2] + kEps2d;
  g.cov_b = g.u[0] * g.v[0] + g.u[1] * g.v[1] + g.u[2] * g.v[2];
  g.cov_c = g.v[0] * g.v[0] + g.v[1] * g.v[1] + g.v[2] * g.v[2] + kEps2d;
  g.det = g.cov_a * g.cov_c - g.cov_b * g.cov_b;
}

// Returns means2d [N, 2], conics [N, 3], depths [N], radii [N, 2] int32, visible [N] bool.
std::vector<torch::Tensor> project(const torch::Tensor& means, const torch::Tensor& quats, const torch::Tensor& scales,
                                   const torch::Tensor& opacities, const torch::Tensor& viewmat,
                                   const torch::Tensor& K, int64_t width, int64_t height) {
  const auto dtype = means.scalar_type();
  check_input(means, "means", 2, dtype);
  check_input(quats, "quats", 2, dtype);
  check_input(scales, "scales", 2, dtype);
  check_input(opacities, "opacities", 1, dtype);
  check_input(viewmat, "viewmat", 2, dtype);
  check_input(K, "K", 2, dtype);
  const int64_t n = means.size(0);
  auto opts = means.options();
  torch::Tensor means2d = torch::zeros({n, 2}, opts), conics = torch::zeros({n, 3}, opts);
  torch::Tensor depths = torch::empty({n}, opts), radii = torch::zeros({n, 2}, opts.dtype(torch::kInt32));
  torch::Tensor visible = torch::zeros({n}, opts.dtype(torch::kBool));
  AT_DISPATCH_FLOATING_TYPES(dtype, "rasterize_cpu_project", [&] {
    const Camera cam = make_camera(viewmat.data_ptr<scalar_t>(), K.data_ptr<scalar_t>(), width, height);
    const scalar_t *mp = means.data_ptr<scalar_t>(), *qp = quats.data_ptr<scalar_t>();
    const scalar_t *sp = scales.data_ptr<scalar_t>(), *op = opacities.data_ptr<scalar_t>();
    scalar_t *m2d = means2d.data_ptr<scalar_t>(), *con = conics.data_ptr<scalar_t>(), *dep = depths.data_ptr<scalar_t>();
    int32_t* rad = radii.data_ptr<int32_t>();
    bool* vis = visible.data_ptr<bool>();
    parallel_over(n, [&](int64_t i) {
      ProjectedGaussian g;
      project_one(cam, mp + 3 * i, qp + 4 * i, sp + 3 * i, g);
      dep[i] = static_cast<scalar_t>(g.z);
      const double opacity = op[i];
      bool ok = g.in_range && g.det > 0 && opacity >= kAlphaMin;
      if (!ok) return;
      const double mx = cam.fx * g.x * g.iz + cam.cx, my = cam.fy * g.y * g.iz + cam.cy;
      const double extent = std::min(std::sqrt(2.0 * std::log(opacity / kAlphaMin)), kMaxExtent);
      const double rx = std::ceil(extent * std::sqrt(std::max(g.cov_a, 0.0)));
      const double ry = std::ceil(extent * std::sqrt(std::max(g.cov_c, 0.0)));
      ok = (rx > 0 || ry > 0) && mx + rx > 0 && mx - rx < width && my + ry > 0 && my - ry < height;
      if (!ok) return;
      vis[i] = true;
      rad[2 * i] = static_cast<int32_t>(rx), rad[2 * i + 1] = static_cast<int32_t>(ry);
      m2d[2 * i] = static_cast<scalar_t>(mx), m2d[2 * i + 1] = static_cast<scalar_t>(my);
      con[3 * i] = static_cast<scalar_t>(g.cov_c / g.det);
      con[3 * i + 1] = static_cast<scalar_t>(-g.cov_b / g.det);
      con[3 * i + 2] = static_cast<scalar_t>(g.cov_a / g.det);
    });
  });
  return {means2d, conics, depths, radii, visible};
}

// Chain rule of `project` for the visible Gaussians (culled ones get zero, as in the torch backend):
// returns the gradients of means [N, 3], quats [N, 4], scales [N, 3].
std::vector<torch::Tensor> project_backward(const torch::Tensor& means, const torch::Tensor& quats,
                                            const torch::Tensor& scales, const torch::Tensor& viewmat,
                                            const torch::Tensor& K, const torch::Tensor& visible,
                                            const torch::Tensor& v_means2d, const torch::Tensor& v_conics,
                                            int64_t width, int64_t height) {
  const auto dtype = means.scalar_type();
  check_input(means, "means", 2, dtype);
  check_input(quats, "quats", 2, dtype);
  check_input(scales, "scales", 2, dtype);
  check_input(viewmat, "viewmat", 2, dtype);
  check_input(K, "K", 2, dtype);
  check_input(visible, "visible", 1, torch::kBool);
  check_input(v_means2d, "v_means2d", 2, dtype);
  check_input(v_conics, "v_conics", 2, dtype);
  const int64_t n = means.size(0);
  auto opts = means.options();
  torch::Tensor g_means = torch::zeros({n, 3}, opts), g_quats = torch::zeros({n, 4}, opts);
  torch::Tensor g_scales = torch::zeros({n, 3}, opts);
  AT_DISPATCH_FLOATING_TYPES(dtype, "rasterize_cpu_project_backward", [&] {
    const Camera cam = make_camera(viewmat.data_ptr<scalar_t>(), K.data_ptr<scalar_t>(), width, height);
    const scalar_t *mp = means.data_ptr<scalar_t>(), *qp = quats.data_ptr<scalar_t>(), *sp = scales.data_ptr<scalar_t>();
    const scalar_t *vm = v_means2d.data_ptr<scalar_t>(), *vc = v_conics.data_ptr<scalar_t>();
    const bool* vis = visible.data_ptr<bool>();
    scalar_t *gm = g_means.data_ptr<scalar_t>(), *gq = g_quats.data_ptr<scalar_t>(), *gs = g_scales.data_ptr<scalar_t>();
    parallel_over(n, [&](int64_t i) {
      if (!vis[i]) return;
      ProjectedGaussian g;
      project_one(cam, mp + 3 * i, qp + 4 * i, sp + 3 * i, g);
      const double A = g.cov_a, B = g.cov_b, C = g.cov_c, D = g.det, D2 = D * D;
      const double v00 = vc[3 * i], v01 = vc[3 * i + 1], v11 = vc[3 * i + 2];
      // conic = (C / D, -B / D, A / D) with D = A C - B^2
      const double v_a = v00 * (-C * C / D2) + v01 * (B * C / D2) + v11 * (1.0 / D - A * C / D2);
      const double v_b = v00 * (2 * B * C / D2) + v01 * (-1.0 / D - 2 * B * B / D2) + v11 * (2 * A * B / D2);
      const double v_c = v00 * (1.0 / D - C * A / D2) + v01 * (B * A / D2) + v11 * (-A * A / D2);
      double v_u[3], v_v[3], v_j0[3] = {0, 0, 0}, v_j1[3] = {0, 0, 0}, v_mc[9];
      for (int k = 0; k < 3; ++k) {
        v_u[k] = 2 * v_a * g.u[k] + v_b * g.v[k];
        v_v[k] = v_b * g.u[k] + 2 * v_c * g.v[k];
      }
      for (int r = 0; r < 3; ++r) {
        for (int k = 0; k < 3; ++k) {
          v_j0[r] += v_u[k] * g.mc[3 * r + k];
          v_j1[r] += v_v[k] * g.mc[3 * r + k];
          v_mc[3 * r + k] = g.j0[r] * v_u[k] + g.j1[r] * v_v[k];
        }
      }
      const double iz = g.iz, iz2 = iz * iz, iz3 = iz2 * iz;
      double v_x = 0, v_y = 0, v_z = 0;
      v_z += v_j0[0] * (-cam.fx * iz2) + v_j0[2] * (2 * cam.fx * g.tx * iz3);
      v_z += v_j1[1] * (-cam.fy * iz2) + v_j1[2] * (2 * cam.fy * g.ty * iz3);
      const double v_tx = v_j0[2] * (-cam.fx * iz2), v_ty = v_j1[2] * (-cam.fy * iz2);
      if (g.clamped_x) v_z += v_tx * g.tx * iz; else v_x += v_tx;  // tx = z * limit, or x
      if (g.clamped_y) v_z += v_ty * g.ty * iz; else v_y += v_ty;
      const double vmx = vm[2 * i], vmy = vm[2 * i + 1];
      v_x += vmx * cam.fx * iz;
      v_y += vmy * cam.fy * iz;
      v_z += -vmx * cam.fx * g.x * iz2 - vmy * cam.fy * g.y * iz2;
      // means: x_c = R_view m + t
      for (int j = 0; j < 3; ++j)
        gm[3 * i + j] = static_cast<scalar_t>(cam.r[j] * v_x + cam.r[3 + j] * v_y + cam.r[6 + j] * v_z);
      // mc = R_view (R_q S): v_ms = R_viewᵀ v_mc; ms[r][k] = rq[r][k] s[k]
      double v_rq[9], v_s[3] = {0, 0, 0};
      for (int r = 0; r < 3; ++r) {
        for (int k = 0; k < 3; ++k) {
          const double v_ms = cam.r[r] * v_mc[k] + cam.r[3 + r] * v_mc[3 + k] + cam.r[6 + r] * v_mc[6 + k];
          v_s[k] += v_ms * g.rq[3 * r + k];
          v_rq[3 * r + k] = v_ms * static_cast<double>(sp[3 * i + k]);
        }
      }
      for (int k = 0; k < 3; ++k) gs[3 * i + k] = static_cast<scalar_t>(v_s[k]);
      const double w = g.n[0], x = g.n[1], y = g.n[2], z = g.n[3];
      const double v_w = 2 * (-z * v_rq[1] + y * v_rq[2] + z * v_rq[3] - x * v_rq[5] - y * v_rq[6] + x * v_rq[7]);
      const double v_qx = 2 * (y * v_rq[1] + z * v_rq[2] + y * v_rq[3] - 2 * x * v_rq[4] - w * v_rq[5] +
                               z * v_rq[6] + w * v_rq[7] - 2 * x * v_rq[8]);
      const double v_qy = 2 * (-2 * y * v_rq[0] + x * v_rq[1] + w * v_rq[2] + x * v_rq[3] + z * v_rq[5] -
                               w * v_rq[6] + z * v_rq[7] - 2 * y * v_rq[8]);
      const double v_qz = 2 * (-2 * z * v_rq[0] - w * v_rq[1] + x * v_rq[2] + w * v_rq[3] - 2 * z * v_rq[4] +
                               y * v_rq[5] + x * v_rq[6] + y * v_rq[7]);
      // through the normalisation q / |q|
      const double dot = w * v_w + x * v_qx + y * v_qy + z * v_qz;
      const double vn[4] = {v_w, v_qx, v_qy, v_qz};
      for (int j = 0; j < 4; ++j) gq[4 * i + j] = static_cast<scalar_t>((vn[j] - g.n[j] * dot) / g.qnorm);
    });
  });
  return {g_means, g_quats, g_scales};
}

// The triangle z-buffer of render/mesh.py (rasterize_mesh): every pixel centre of each triangle's box, the inside
// test and the depth in float32, the step-by-step arithmetic of mesh.py's _rasterize_pieces (no FMA contraction:
// CFLAGS), so both write the same keys bit for bit; a pixel keeps the smallest key (z's float32 bits << 32 | face
// id: nearest first, then the smaller id), whatever the order. One thread: a head mesh takes ~1 ms at 256 px.
void mesh_zbuffer(const torch::Tensor& table, const torch::Tensor& inv_z, const torch::Tensor& face_ids,
                  const torch::Tensor& box, int64_t width, torch::Tensor zbuf) {
  using geoavatar_native::check_input;
  check_input(table, "table", 2, torch::kFloat32);  // [F, 6]: vertex-0 x, y; d(b1, b2)/dx; d(b1, b2)/dy
  check_input(inv_z, "inv_z", 2, torch::kFloat32);  // [F, 3]
  check_input(face_ids, "face_ids", 1, torch::kInt64);  // [F]
  check_input(box, "box", 2, torch::kInt64);  // [F, 4]: first and last pixel column and row, inside the image
  check_input(zbuf, "zbuf", 1, torch::kInt64);  // [H * W], updated in place
  const int64_t n = table.size(0);
  TORCH_CHECK(table.size(1) == 6 && inv_z.size(0) == n && inv_z.size(1) == 3 && face_ids.size(0) == n &&
                  box.size(0) == n && box.size(1) == 4 && width > 0,
              "mesh_zbuffer: expected table [F, 6], inv_z [F, 3], face_ids [F], box [F, 4] and a positive width");
  const float* tp = table.data_ptr<float>();
  const float* izp = inv_z.data_ptr<float>();
  const int64_t* ids = face_ids.data_ptr<int64_t>();
  const int64_t* bp = box.data_ptr<int64_t>();
  int64_t* keys = zbuf.data_ptr<int64_t>();
  const int64_t pixels = zbuf.size(0);
  const float eps = 1e-5f;  // mesh.py's _INSIDE_EPS
  for (int64_t f = 0; f < n; ++f) {
    const float* t = tp + 6 * f;
    const float* iz = izp + 3 * f;
    const int64_t* b = bp + 4 * f;
    TORCH_CHECK(b[0] >= 0 && b[1] >= 0 && b[2] < width && (b[3] + 1) * width <= pixels,
                "mesh_zbuffer: a triangle's box leaves the image");
    for (int64_t py = b[1]; py <= b[3]; ++py) {
      const float dy = (static_cast<float>(py) + 0.5f) - t[1];
      for (int64_t px = b[0]; px <= b[2]; ++px) {
        const float dx = (static_cast<float>(px) + 0.5f) - t[0];
        const float b1 = dx * t[2] + dy * t[4];
        const float b2 = dx * t[3] + dy * t[5];
        const float b0 = (1.0f - b1) - b2;
        if (!(b0 >= -eps && b1 >= -eps && b2 >= -eps)) continue;
        const float c0 = std::max(b0, 0.0f), c1 = std::max(b1, 0.0f), c2 = std::max(b2, 0.0f);
        const float depth = ((c0 + c1) + c2) / ((c0 * iz[0] + c1 * iz[1]) + c2 * iz[2]);
        int32_t bits;
        std::memcpy(&bits, &depth, sizeof(bits));
        const int64_t key = (static_cast<int64_t>(bits) << 32) | ids[f];
        int64_t& kept = keys[py * width + px];
        if (key < kept) kept = key;
      }
    }
  }
}

}  // namespace

PYBIND11_MODULE(TORCH_EXTENSION_NAME, module) {
  module.doc() = "geoavatar native CPU rasterize-to-pixels (tile binning, compositing, backward)";
  using geoavatar_native::release_gil;  // other Python threads run during a frame
  module.def("forward", &forward, "rgb, alpha, tile offsets, tile ids, last, t_final", release_gil());
  module.def("backward", &backward, "grads of means2d, conics, opacities, colors", release_gil());
  module.def("project", &project, "means2d, conics, depths, radii, visible of one camera", release_gil());
  module.def("project_backward", &project_backward, "grads of means, quats, scales", release_gil());
  module.def("mesh_zbuffer", &mesh_zbuffer, "render/mesh.py's triangle z-buffer, in place", release_gil());
  module.def("simd_paths", &simd_paths, "SIMD paths of the float32 compositing this CPU runs, fastest first");
  module.def("max_threads", []() { return omp_get_max_threads(); });
}
