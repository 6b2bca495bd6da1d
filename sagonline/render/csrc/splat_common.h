// What the compiled rasterizer (raster_cpu.cpp) and the compiled vote (vote_cpu.cpp) share: the
// support and alpha rules of sagonline/render/projection.py, a tile's pixel span, the tile
// scheduler and the tile lists.
#pragma once

#include <optional>
// ATen and torch's tensor types only: torch/extension.h, the whole C++ frontend, takes two and
// a half times as long to compile, in each source file
#include <torch/types.h>
#include <ATen/Parallel.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <thread>
#include <vector>

namespace splat {

constexpr float kCutoff2 = 9.0f;  // 3-sigma support, squared
constexpr float kSurfelFilter = 2.0f;
constexpr float kAlphaMin = 1.0f / 255.0f;
constexpr float kAlphaMax = 0.99f;

// The pixels of a tile a splat's bounding box covers: [x0, x1) x [y0, y1) in tile-local units.
struct Span {
  int x0, x1, y0, y1;
};

inline Span clip(const float* box, int64_t tx0, int64_t ty0, int tile) {
  // pixel centre x + 0.5 must lie in [xmin, xmax]; a 0.01 px margin keeps rounding at the
  // support's edge on the safe side (the response itself still decides)
  constexpr float m = 0.01f;
  Span s;
  s.x0 = std::max(0, static_cast<int>(std::ceil(box[0] - 0.5f - m - tx0)));
  s.x1 = std::min(tile, static_cast<int>(std::floor(box[1] - 0.5f + m - tx0)) + 1);
  s.y0 = std::max(0, static_cast<int>(std::ceil(box[2] - 0.5f - m - ty0)));
  s.y1 = std::min(tile, static_cast<int>(std::floor(box[3] - 0.5f + m - ty0)) + 1);
  return s;
}

// The kernels' own thread count: set_kernel_threads(n) (0: torch's, at::get_num_threads()). A
// fit runs torch's own ops on one thread (their vector loops then always split the same way)
// and gives the kernels the machine's threads through this.
inline std::atomic<int> g_kernel_threads{0};
inline int kernel_threads() {
  const int n = g_kernel_threads.load();
  return n > 0 ? n : at::get_num_threads();
}

// Runs fn(tile) for every tile on kernel_threads() threads that take tiles one at a time
// (busy tiles cluster on the object, so a static split would leave one thread idle) and block,
// not spin, when done: a vote beside another process on shared cores does not fight it.
template <typename Fn>
void for_each_tile(int64_t n_tiles, const Fn& fn) {
  std::atomic<int64_t> next{0};
  auto worker = [&]() {
    for (int64_t ti = next++; ti < n_tiles; ti = next++) fn(ti);
  };
  const int threads =
      static_cast<int>(std::max<int64_t>(1, std::min<int64_t>({kernel_threads(), 64, n_tiles})));
  std::vector<std::thread> pool;
  for (int t = 1; t < threads; ++t) pool.emplace_back(worker);
  worker();
  for (auto& t : pool) t.join();
}

}  // namespace splat

// Tile lists (raster_cpu.cpp): per tile, the splats whose box touches it, front to back.
std::vector<torch::Tensor> bin_tiles(torch::Tensor bbox, torch::Tensor by_depth, int64_t ntx,
                                     int64_t nty, int64_t tile);

// The compiled vote (vote_cpu.cpp).
std::vector<torch::Tensor> prepare_view(bool surfel, torch::Tensor means, torch::Tensor quats,
                                        torch::Tensor scales, torch::Tensor opacities,
                                        torch::Tensor rotation, torch::Tensor translation,
                                        torch::Tensor intrinsics, int64_t width, int64_t height,
                                        double near, int64_t tile);
int64_t vote(bool surfel, torch::Tensor ids, torch::Tensor params, torch::Tensor spans,
             torch::Tensor order, torch::Tensor offsets, torch::Tensor counts, int64_t width,
             int64_t height, int64_t tile, torch::Tensor labels, int64_t num_labels, double eps,
             std::optional<double> delta, bool weighted, torch::Tensor hist);
std::string vote_simd();
