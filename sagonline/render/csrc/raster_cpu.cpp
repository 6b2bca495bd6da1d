// Differentiable tile rasterizer for the CPU: the same compositing as
// sagonline/render/rasterize.py (3DGS EWA splats and 2DGS ray-splat surfels, alpha clipped at
// 0.99, skipped below 1/255, a pixel ends at the first splat that would bring its
// transmittance under t_stop), with a hand-written backward pass (back to front, as the 3DGS
// reference does) instead of autograd over per-block tensors.
//
// Inputs are the tile lists built in Python: `order` (E,) splat indices sorted by (tile, depth),
// `offsets`/`counts` (n_tiles,). Splat parameters are packed as in ProjectedSplats.params():
// [mx, my, opacity, depth, then conic a, b, c (3DGS) or the 3x3 transform M row-major (2DGS)].

#include "splat_common.h"
// the Python bindings at the end: pybind11 and its tensor casters, without the rest of
// torch/extension.h (the C++ frontend: half of the kernels' compile time)
#include <torch/csrc/utils/pybind.h>

#include <algorithm>
#include <cmath>
#include <vector>

using namespace splat;

namespace {

struct Response {
  float alpha = 0.f;   // after clipping; 0 when the splat does not reach the pixel
  float raw = 0.f;     // opacity * exp(power) before the 0.99 clip
  float gauss = 0.f;   // exp(power)
  float depth = 0.f;   // depth where the ray meets the splat
  // 2DGS intermediates for the backward pass
  bool use3d = false;
  float u = 0.f, v = 0.f, pz = 1.f;
  bool pz_clamped = false;
  float k[3] = {0, 0, 0}, l[3] = {0, 0, 0};
};

inline Response respond(bool surfel, const float* p, float px, float py) {
  Response r;
  const float dx = px - p[0], dy = py - p[1];
  float power;
  bool inside;
  if (!surfel) {
    const float a = p[4], b = p[5], c = p[6];
    power = -0.5f * (a * dx * dx + c * dy * dy) - b * dx * dy;
    inside = power >= -0.5f * kCutoff2;
    r.depth = p[3];
  } else {
    const float* m = p + 4;
    for (int i = 0; i < 3; ++i) {
      r.k[i] = px * m[6 + i] - m[i];
      r.l[i] = py * m[6 + i] - m[3 + i];
    }
    float pz = r.k[0] * r.l[1] - r.k[1] * r.l[0];
    if (std::fabs(pz) < 1e-12f) {
      pz = 1e-12f;
      r.pz_clamped = true;
    }
    r.pz = pz;
    r.u = (r.k[1] * r.l[2] - r.k[2] * r.l[1]) / pz;
    r.v = (r.k[2] * r.l[0] - r.k[0] * r.l[2]) / pz;
    const float rho3d = r.u * r.u + r.v * r.v;
    const float rho2d = kSurfelFilter * (dx * dx + dy * dy);
    r.use3d = rho3d <= rho2d;
    const float rho = r.use3d ? rho3d : rho2d;
    r.depth = r.use3d ? r.u * m[6] + r.v * m[7] + m[8] : p[3];
    power = -0.5f * rho;
    inside = (rho <= kCutoff2) && (r.depth > 1e-2f);
  }
  if (!inside) return r;  // alpha stays 0; no exp for the (many) pairs outside the support
  r.gauss = std::exp(power);
  r.raw = p[2] * r.gauss;
  const float alpha = std::min(r.raw, kAlphaMax);
  r.alpha = alpha >= kAlphaMin ? alpha : 0.f;
  return r;
}

// Gradient of (alpha, depth) w.r.t. the packed parameters, added into g (K floats).
inline void respond_backward(bool surfel, const float* p, float px, float py, const Response& r,
                             float g_alpha, float g_depth, float* g) {
  const float dx = px - p[0], dy = py - p[1];
  float g_power = 0.f;
  if (r.raw < kAlphaMax) {  // clipped alphas pass no gradient (as clamp_max in autograd)
    g[2] += g_alpha * r.gauss;
    g_power = g_alpha * r.raw;
  }
  if (!surfel) {
    const float a = p[4], b = p[5], c = p[6];
    g[0] += g_power * (a * dx + b * dy);
    g[1] += g_power * (c * dy + b * dx);
    g[4] += g_power * (-0.5f * dx * dx);
    g[5] += g_power * (-dx * dy);
    g[6] += g_power * (-0.5f * dy * dy);
    g[3] += g_depth;
    return;
  }
  const float g_rho = -0.5f * g_power;
  float* gm = g + 4;
  const float* m = p + 4;
  if (!r.use3d) {
    g[0] += g_rho * kSurfelFilter * (-2.f * dx);
    g[1] += g_rho * kSurfelFilter * (-2.f * dy);
    g[3] += g_depth;
    return;
  }
  const float gu = g_rho * 2.f * r.u + g_depth * m[6];
  const float gv = g_rho * 2.f * r.v + g_depth * m[7];
  gm[6] += g_depth * r.u;
  gm[7] += g_depth * r.v;
  gm[8] += g_depth;
  const float g_nu = gu / r.pz, g_nv = gv / r.pz;
  const float g_pz = r.pz_clamped ? 0.f : -(gu * r.u + gv * r.v) / r.pz;
  const float* k = r.k;
  const float* l = r.l;
  float gk[3] = {0, 0, 0}, gl[3] = {0, 0, 0};
  // nu = k1 l2 - k2 l1
  gk[1] += l[2] * g_nu;
  gl[2] += k[1] * g_nu;
  gk[2] -= l[1] * g_nu;
  gl[1] -= k[2] * g_nu;
  // nv = k2 l0 - k0 l2
  gk[2] += l[0] * g_nv;
  gl[0] += k[2] * g_nv;
  gk[0] -= l[2] * g_nv;
  gl[2] -= k[0] * g_nv;
  // pz = k0 l1 - k1 l0
  gk[0] += l[1] * g_pz;
  gl[1] += k[0] * g_pz;
  gk[1] -= l[0] * g_pz;
  gl[0] -= k[1] * g_pz;
  for (int i = 0; i < 3; ++i) {
    gm[i] -= gk[i];
    gm[6 + i] += px * gk[i] + py * gl[i];
    gm[3 + i] -= gl[i];
  }
}

struct Raster {
  bool surfel;
  int64_t width, height, tile, tiles_x, K, C;
  const float *params, *colors, *boxes;
  const int64_t *order, *offsets, *counts;
};

// Walk one tile front to back: per pixel feat (C), depth, final T and walked count.
void forward_tile(const Raster& R, int64_t ti, float stop, float* F, float* D, float* TT,
                  int32_t* L, int64_t* BI) {
  const int tile = static_cast<int>(R.tile);
  const int64_t tx0 = (ti % R.tiles_x) * R.tile, ty0 = (ti / R.tiles_x) * R.tile;
  const int npix = tile * tile;
  std::vector<float> T(npix, 1.f), dep(npix, 0.f), feat(npix * R.C, 0.f);
  std::vector<int32_t> walked(npix, 0);
  std::vector<char> done(npix, 0);
  std::vector<float> best_w(npix, 0.f);  // the most visible splat: largest alpha_i T_i
  std::vector<int64_t> best(npix, -1);
  int active = 0;
  for (int q = 0; q < npix; ++q) {
    const int64_t x = tx0 + q % tile, y = ty0 + q / tile;
    if (x >= R.width || y >= R.height) {
      done[q] = 1;
    } else {
      ++active;
    }
  }
  const int64_t n = R.counts[ti], base = R.offsets[ti];
  for (int64_t j = 0; j < n && active > 0; ++j) {
    const int64_t s = R.order[base + j];
    const float* p = R.params + s * R.K;
    const Span sp = clip(R.boxes + s * 4, tx0, ty0, tile);
    for (int ly = sp.y0; ly < sp.y1; ++ly) {
      for (int lx = sp.x0; lx < sp.x1; ++lx) {
        const int q = ly * tile + lx;
        if (done[q]) continue;
        const Response r = respond(R.surfel, p, tx0 + lx + 0.5f, ty0 + ly + 0.5f);
        if (r.alpha <= 0.f) continue;
        const float next = T[q] * (1.f - r.alpha);
        if (next < stop) {  // T only falls: this pixel is finished
          done[q] = 1;
          --active;
          continue;
        }
        const float w = r.alpha * T[q];
        for (int64_t c = 0; c < R.C; ++c) feat[q * R.C + c] += w * R.colors[s * R.C + c];
        dep[q] += w * r.depth;
        if (w > best_w[q]) {
          best_w[q] = w;
          best[q] = s;
        }
        T[q] = next;
        walked[q] = static_cast<int32_t>(j + 1);
      }
    }
  }
  for (int q = 0; q < npix; ++q) {
    const int64_t x = tx0 + q % tile, y = ty0 + q / tile;
    if (x >= R.width || y >= R.height) continue;
    const int64_t pix = y * R.width + x;
    for (int64_t c = 0; c < R.C; ++c) F[pix * R.C + c] = feat[q * R.C + c];
    D[pix] = dep[q];
    TT[pix] = T[q];
    L[pix] = walked[q];
    BI[pix] = best[q];
  }
}

// Walk one tile front to back for up to 8 groups of splats at once (`groups`: a bit per group
// per splat): per group and pixel its alpha-weighted depth and final T, each group composited as
// forward_tile composites a render of its own splats alone (the same order, stop and arithmetic;
// a splat's response is computed once for all its groups).
void coverage_tile(const Raster& R, int64_t ti, float stop, const uint8_t* groups, int G,
                   float* D, float* TT) {
  const int tile = static_cast<int>(R.tile);
  const int64_t tx0 = (ti % R.tiles_x) * R.tile, ty0 = (ti / R.tiles_x) * R.tile;
  const int npix = tile * tile;
  std::vector<float> T(G * npix, 1.f), dep(G * npix, 0.f);
  std::vector<char> done(G * npix, 0);
  int64_t active = 0;
  for (int q = 0; q < npix; ++q) {
    const int64_t x = tx0 + q % tile, y = ty0 + q / tile;
    for (int g = 0; g < G; ++g) done[g * npix + q] = x >= R.width || y >= R.height;
    if (x < R.width && y < R.height) active += G;
  }
  const int64_t n = R.counts[ti], base = R.offsets[ti];
  for (int64_t j = 0; j < n && active > 0; ++j) {
    const int64_t s = R.order[base + j];
    const uint8_t bits = groups[s];
    if (bits == 0) continue;
    const float* p = R.params + s * R.K;
    const Span sp = clip(R.boxes + s * 4, tx0, ty0, tile);
    for (int ly = sp.y0; ly < sp.y1; ++ly) {
      for (int lx = sp.x0; lx < sp.x1; ++lx) {
        const int q = ly * tile + lx;
        bool walking = false;
        for (int g = 0; g < G; ++g) walking |= ((bits >> g) & 1) && !done[g * npix + q];
        if (!walking) continue;
        const Response r = respond(R.surfel, p, tx0 + lx + 0.5f, ty0 + ly + 0.5f);
        if (r.alpha <= 0.f) continue;
        for (int g = 0; g < G; ++g) {
          const int i = g * npix + q;
          if (!((bits >> g) & 1) || done[i]) continue;
          const float next = T[i] * (1.f - r.alpha);
          if (next < stop) {  // T only falls: this group is finished at this pixel
            done[i] = 1;
            --active;
            continue;
          }
          const float w = r.alpha * T[i];
          dep[i] += w * r.depth;
          T[i] = next;
        }
      }
    }
  }
  const int64_t plane = R.width * R.height;
  for (int q = 0; q < npix; ++q) {
    const int64_t x = tx0 + q % tile, y = ty0 + q / tile;
    if (x >= R.width || y >= R.height) continue;
    for (int g = 0; g < G; ++g) {
      D[g * plane + y * R.width + x] = dep[g * npix + q];
      TT[g * plane + y * R.width + x] = T[g * npix + q];
    }
  }
}

// Walk one tile back to front, adding parameter and colour gradients into GP, GC.
void backward_tile(const Raster& R, int64_t ti, const float* TT, const int32_t* L,
                   const float* GF, const float* GD, const float* GT, float* GP, float* GC) {
  const int tile = static_cast<int>(R.tile);
  const int64_t tx0 = (ti % R.tiles_x) * R.tile, ty0 = (ti / R.tiles_x) * R.tile;
  const int npix = tile * tile;
  std::vector<float> T(npix, 1.f), after(npix * R.C, 0.f), depth_after(npix, 0.f);
  std::vector<int32_t> last(npix, 0);
  std::vector<int64_t> pix(npix, -1);
  int32_t longest = 0;
  for (int q = 0; q < npix; ++q) {
    const int64_t x = tx0 + q % tile, y = ty0 + q / tile;
    if (x >= R.width || y >= R.height) continue;
    pix[q] = y * R.width + x;
    T[q] = TT[pix[q]];
    last[q] = L[pix[q]];
    longest = std::max(longest, last[q]);
  }
  const int64_t base = R.offsets[ti];
  for (int64_t j = longest - 1; j >= 0; --j) {
    const int64_t s = R.order[base + j];
    const float* p = R.params + s * R.K;
    const Span sp = clip(R.boxes + s * 4, tx0, ty0, tile);
    for (int ly = sp.y0; ly < sp.y1; ++ly) {
      for (int lx = sp.x0; lx < sp.x1; ++lx) {
        const int q = ly * tile + lx;
        if (pix[q] < 0 || j >= last[q]) continue;
        const float px = tx0 + lx + 0.5f, py = ty0 + ly + 0.5f;
        const Response r = respond(R.surfel, p, px, py);
        if (r.alpha <= 0.f) continue;
        const float one_minus = 1.f - r.alpha;
        const float T_before = T[q] / one_minus;
        const float w = r.alpha * T_before;
        const float* gf = GF + pix[q] * R.C;
        float* aft = after.data() + q * R.C;
        // d out / d alpha_j = T_j c_j - (sum of later contributions) / (1 - alpha_j)
        float g_alpha = 0.f;
        for (int64_t c = 0; c < R.C; ++c) {
          const float col = R.colors[s * R.C + c];
          g_alpha += gf[c] * (T_before * col - aft[c] / one_minus);
          GC[s * R.C + c] += w * gf[c];
          aft[c] += w * col;
        }
        const float gd = GD[pix[q]];
        g_alpha += gd * (T_before * r.depth - depth_after[q] / one_minus);
        g_alpha += GT[pix[q]] * (-TT[pix[q]] / one_minus);
        depth_after[q] += w * r.depth;
        respond_backward(R.surfel, p, px, py, r, g_alpha, gd * w, GP + s * R.K);
        T[q] = T_before;
      }
    }
  }
}

Raster make_raster(bool surfel, const torch::Tensor& params, const torch::Tensor& colors,
                   const torch::Tensor& boxes, const torch::Tensor& order,
                   const torch::Tensor& offsets, const torch::Tensor& counts, int64_t width,
                   int64_t height, int64_t tile) {
  TORCH_CHECK(params.is_contiguous() && colors.is_contiguous() && boxes.is_contiguous(),
              "rasterizer inputs must be contiguous");
  TORCH_CHECK(params.dtype() == torch::kFloat32 && colors.dtype() == torch::kFloat32 &&
                  boxes.dtype() == torch::kFloat32,
              "rasterizer inputs must be float32");
  TORCH_CHECK(params.size(1) == (surfel ? 13 : 7), "packed splat parameters have wrong width");
  return Raster{surfel,
                width,
                height,
                tile,
                (width + tile - 1) / tile,
                params.size(1),
                colors.size(1),
                params.data_ptr<float>(),
                colors.data_ptr<float>(),
                boxes.data_ptr<float>(),
                order.data_ptr<int64_t>(),
                offsets.data_ptr<int64_t>(),
                counts.data_ptr<int64_t>()};
}

}  // namespace

// Returns feat (H, W, C), depth (H, W), final transmittance (H, W), per pixel the number of
// list entries walked up to and including its last composited splat (int32, for backward), and
// the most visible splat (largest blend weight; -1 where none is composited).
std::vector<torch::Tensor> forward(bool surfel, torch::Tensor params, torch::Tensor colors,
                                   torch::Tensor boxes, torch::Tensor order,
                                   torch::Tensor offsets, torch::Tensor counts, int64_t width,
                                   int64_t height, int64_t tile, double t_stop) {
  params = params.contiguous();
  colors = colors.contiguous();
  boxes = boxes.contiguous();
  const Raster R =
      make_raster(surfel, params, colors, boxes, order, offsets, counts, width, height, tile);
  auto feat = torch::zeros({height, width, R.C}, params.options());
  auto depth = torch::zeros({height, width}, params.options());
  auto final_T = torch::ones({height, width}, params.options());
  auto last = torch::zeros({height, width}, order.options().dtype(torch::kInt32));
  auto best = torch::full({height, width}, -1, order.options().dtype(torch::kInt64));
  float* F = feat.data_ptr<float>();
  float* D = depth.data_ptr<float>();
  float* TT = final_T.data_ptr<float>();
  int32_t* L = last.data_ptr<int32_t>();
  int64_t* BI = best.data_ptr<int64_t>();
  const float stop = static_cast<float>(t_stop);
  for_each_tile(counts.size(0), [&](int64_t ti) {
    if (R.counts[ti] > 0) forward_tile(R, ti, stop, F, D, TT, L, BI);
  });
  return {feat, depth, final_T, last, best};
}

// Returns, per group of splats (`groups` (M,) uint8, a bit per group, G <= 8 groups), the
// alpha-weighted depth (G, H, W) and final transmittance (G, H, W) that `forward` gives for a
// render of that group's splats alone, from one walk over the tile lists of all of them.
std::vector<torch::Tensor> coverage(bool surfel, torch::Tensor params, torch::Tensor boxes,
                                    torch::Tensor order, torch::Tensor offsets,
                                    torch::Tensor counts, torch::Tensor groups,
                                    int64_t num_groups, int64_t width, int64_t height,
                                    int64_t tile, double t_stop) {
  params = params.contiguous();
  boxes = boxes.contiguous();
  groups = groups.contiguous();
  TORCH_CHECK(num_groups >= 1 && num_groups <= 8, "coverage: 1 to 8 groups");
  TORCH_CHECK(groups.dtype() == torch::kUInt8 && groups.size(0) == params.size(0),
              "coverage: groups must be uint8, one per splat");
  const auto colors = torch::zeros({params.size(0), 0}, params.options());
  const Raster R =
      make_raster(surfel, params, colors, boxes, order, offsets, counts, width, height, tile);
  auto depth = torch::zeros({num_groups, height, width}, params.options());
  auto final_T = torch::ones({num_groups, height, width}, params.options());
  float* D = depth.data_ptr<float>();
  float* TT = final_T.data_ptr<float>();
  const uint8_t* Gp = groups.data_ptr<uint8_t>();
  const int G = static_cast<int>(num_groups);
  const float stop = static_cast<float>(t_stop);
  for_each_tile(counts.size(0), [&](int64_t ti) {
    if (R.counts[ti] > 0) coverage_tile(R, ti, stop, Gp, G, D, TT);
  });
  return {depth, final_T};
}

constexpr int64_t kParts = 16;  // runs of tiles with a gradient buffer each (see backward)
torch::Tensor sum_parts(const torch::Tensor& all);

// Gradients w.r.t. params (M, K) and colors (M, C) from gradients on feat, depth, final_T.
std::vector<torch::Tensor> backward(bool surfel, torch::Tensor params, torch::Tensor colors,
                                    torch::Tensor boxes, torch::Tensor order,
                                    torch::Tensor offsets, torch::Tensor counts, int64_t width,
                                    int64_t height, int64_t tile, torch::Tensor final_T,
                                    torch::Tensor last, torch::Tensor g_feat,
                                    torch::Tensor g_depth, torch::Tensor g_T) {
  params = params.contiguous();
  colors = colors.contiguous();
  boxes = boxes.contiguous();
  g_feat = g_feat.contiguous();
  g_depth = g_depth.contiguous();
  g_T = g_T.contiguous();
  const Raster R =
      make_raster(surfel, params, colors, boxes, order, offsets, counts, width, height, tile);
  const int64_t M = params.size(0), n_tiles = counts.size(0);
  // The tiles are cut into kParts fixed runs, whatever the thread count; each run adds its
  // tiles' gradients, in tile order, into a buffer of its own, and the buffers are summed in
  // run order: the same sums in the same order on 1 or 64 threads (bit-identical fits).
  const int64_t parts = std::max<int64_t>(1, std::min<int64_t>(kParts, n_tiles));
  auto gp_all = torch::zeros({parts, M, R.K}, params.options());
  auto gc_all = torch::zeros({parts, M, R.C}, params.options());
  const float* TT = final_T.data_ptr<float>();
  const int32_t* L = last.data_ptr<int32_t>();
  const float* GF = g_feat.data_ptr<float>();
  const float* GD = g_depth.data_ptr<float>();
  const float* GT = g_T.data_ptr<float>();
  float* GP0 = gp_all.data_ptr<float>();
  float* GC0 = gc_all.data_ptr<float>();
  for_each_tile(parts, [&](int64_t part) {
    const int64_t begin = part * n_tiles / parts, end = (part + 1) * n_tiles / parts;
    for (int64_t ti = begin; ti < end; ++ti) {
      if (R.counts[ti] == 0) continue;
      backward_tile(R, ti, TT, L, GF, GD, GT, GP0 + part * M * R.K, GC0 + part * M * R.C);
    }
  });
  return {sum_parts(gp_all), sum_parts(gc_all)};
}

// (P, M, K) -> (M, K): each element summed over P in order (deterministic on any threads).
torch::Tensor sum_parts(const torch::Tensor& all) {
  const int64_t P = all.size(0), n = all[0].numel();
  auto out = torch::zeros_like(all[0]);
  const float* a = all.data_ptr<float>();
  float* o = out.data_ptr<float>();
  at::parallel_for(0, n, 4096, [&](int64_t begin, int64_t end) {
    for (int64_t i = begin; i < end; ++i) {
      float acc = 0.f;
      for (int64_t p = 0; p < P; ++p) acc += a[p * n + i];
      o[i] = acc;
    }
  });
  return out;
}

// Tile lists, as rasterize.bin_tiles builds them (same order): every splat's bounding box
// [x0, x1) x [y0, y1) in tiles, splats listed per tile in the order of `by_depth` (splat
// indices sorted by depth, stable). A counting sort, O(splats + intersections), run by bands of
// tile rows in parallel: each band counts and fills only its own tiles, so the lists are the
// same on any number of threads.
std::vector<torch::Tensor> bin_tiles(torch::Tensor bbox, torch::Tensor by_depth, int64_t ntx,
                                     int64_t nty, int64_t tile) {
  bbox = bbox.contiguous();
  by_depth = by_depth.contiguous();
  TORCH_CHECK(bbox.dtype() == torch::kFloat32, "bbox: float32");
  const int64_t m = bbox.size(0), n_tiles = ntx * nty;
  const float* B = bbox.data_ptr<float>();
  const int64_t* D = by_depth.data_ptr<int64_t>();
  const float ts = static_cast<float>(tile);
  std::vector<int32_t> rect(4 * m);
  auto cell = [](float v, int64_t hi) {
    return static_cast<int32_t>(std::min<int64_t>(std::max<int64_t>(static_cast<int64_t>(v), 0), hi));
  };
  at::parallel_for(0, m, 4096, [&](int64_t begin, int64_t end) {
    for (int64_t i = begin; i < end; ++i) {
      const float* b = B + 4 * i;
      int32_t* r = rect.data() + 4 * i;
      r[0] = cell(std::floor(b[0] / ts), ntx);
      r[1] = cell(std::floor(b[1] / ts) + 1.f, ntx);
      r[2] = cell(std::floor(b[2] / ts), nty);
      r[3] = cell(std::floor(b[3] / ts) + 1.f, nty);
    }
  });
  auto counts = torch::zeros({n_tiles}, by_depth.options());
  int64_t* C = counts.data_ptr<int64_t>();
  const int64_t bands = std::max<int64_t>(1, std::min<int64_t>(nty, 4 * kernel_threads()));
  auto band_rows = [&](int64_t band, int32_t& lo, int32_t& hi) {
    lo = static_cast<int32_t>(band * nty / bands);
    hi = static_cast<int32_t>((band + 1) * nty / bands);
  };
  for_each_tile(bands, [&](int64_t band) {
    int32_t lo, hi;
    band_rows(band, lo, hi);
    for (int64_t i = 0; i < m; ++i) {
      const int32_t* r = rect.data() + 4 * i;
      for (int32_t ty = std::max(r[2], lo); ty < std::min(r[3], hi); ++ty)
        for (int32_t tx = r[0]; tx < r[1]; ++tx) ++C[ty * ntx + tx];
    }
  });
  auto offsets = torch::zeros({n_tiles}, by_depth.options());
  int64_t* O = offsets.data_ptr<int64_t>();
  int64_t total = 0;
  for (int64_t t = 0; t < n_tiles; ++t) {
    O[t] = total;
    total += C[t];
  }
  auto order = torch::empty({total}, by_depth.options());
  int64_t* Ord = order.data_ptr<int64_t>();
  std::vector<int64_t> fill(O, O + n_tiles);
  for_each_tile(bands, [&](int64_t band) {
    int32_t lo, hi;
    band_rows(band, lo, hi);
    for (int64_t k = 0; k < m; ++k) {
      const int64_t i = D[k];
      const int32_t* r = rect.data() + 4 * i;
      for (int32_t ty = std::max(r[2], lo); ty < std::min(r[3], hi); ++ty)
        for (int32_t tx = r[0]; tx < r[1]; ++tx) Ord[fill[ty * ntx + tx]++] = i;
    }
  });
  return {order, offsets, counts};
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("set_kernel_threads", [](int n) { splat::g_kernel_threads = n; },
        "threads of the kernels' tile loops (0: torch's thread count)");
  m.def("bin_tiles", &bin_tiles, "per-tile splat lists sorted by depth (CPU)");
  m.def("prepare_view", &prepare_view, "project, depth-sort and bin one view's splats (CPU)");
  m.def("vote", &vote, "trace-and-vote pass into a per-Gaussian label histogram (CPU)");
  m.def("vote_simd", &vote_simd, "the instruction set the vote's walk runs with");
  m.def("forward", &forward, "tile rasterizer forward (CPU)");
  m.def("coverage", &coverage, "each group of splats' depth and final T, one walk (CPU)");
  m.def("backward", &backward, "tile rasterizer backward (CPU)");
}
