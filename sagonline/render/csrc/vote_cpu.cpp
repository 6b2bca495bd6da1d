// The vote's compiled CPU walk, at the floor of the CPU: over the tile lists `prepare_view`
// makes (prepare_view.cpp: projection, depth sort, tile lists), a walk that evaluates a tile row
// of 8 pixels per instruction.
//
// vote: every pixel of every tile walks its splats front to back while T > eps; a splat that
//   reaches the pixel (alpha > 0) votes for the pixel's label when, in addition, its projected
//   centre is closer than delta (if given): +1, or alpha_i T_i when weighted. Votes are
//   summed per (splat, label) inside a tile before they reach the histogram, and tiles are
//   added in tile order: the histogram does not depend on the thread count.
//
// The row walk is written once with GCC vector types (8 floats); it is compiled twice, for AVX2
// and for the baseline instruction set, and the AVX2 build is chosen at run time when the
// processor has it. Both run the same float operations in the same order (no FMA contraction,
// the same polynomial exp), so they give the same histogram bit for bit.

#include <limits>
#include <optional>
#include "splat_common.h"

#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <string>

using namespace splat;

namespace {

typedef float v8f __attribute__((vector_size(32)));
typedef int32_t v8i __attribute__((vector_size(32)));
#define INLINE inline __attribute__((always_inline))

// exp for x <= 0 (Cephes' expf: range reduction by ln 2, degree-6 polynomial; <= 2 ulp from
// the correctly rounded value, as libm's and torch's exp are, so a pair can fall on the other
// side of a threshold only where float32 rounding already decides it).
INLINE v8f exp8(v8f x) {
  const v8f lo = v8f{} - 87.0f;
  x = x < lo ? lo : x;
  const v8f shift = v8f{} + 12582912.0f;  // 1.5 * 2^23: adding it rounds to an integer
  const v8f n = (x * 1.44269504088896341f + shift) - shift;
  v8f r = x - n * 0.693359375f;
  r = r - n * -2.12194440e-4f;
  v8f p = v8f{} + 1.9875691500e-4f;
  p = p * r + 1.3981999507e-3f;
  p = p * r + 8.3334519073e-3f;
  p = p * r + 4.1665795894e-2f;
  p = p * r + 1.6666665459e-1f;
  p = p * r + 5.0000001201e-1f;
  const v8f e = p * r * r + r + 1.0f;
  const v8i bits = (__builtin_convertvector(n, v8i) + 127) << 23;
  return e * (v8f)bits;
}

template <bool Avx2>
INLINE uint32_t lane_bits(v8i m) {
  if constexpr (Avx2) return static_cast<uint32_t>(__builtin_ia32_movmskps256((v8f)m));
  uint32_t b = 0;
  for (int l = 0; l < 8; ++l) b |= static_cast<uint32_t>(m[l] & 1) << l;
  return b;
}

// Alpha of one splat at the 8 pixel centres (xs, py) of a tile row; 0 outside its support.
template <bool Surfel>
INLINE v8f row_alpha(const float* p, v8f xs, float py) {
  const v8f dx = xs - p[0];
  const float dy = py - p[1];
  v8f power;
  v8i inside;
  if constexpr (!Surfel) {
    power = -0.5f * (p[4] * dx * dx + p[6] * dy * dy) - p[5] * dx * dy;
    inside = power >= -0.5f * kCutoff2;
  } else {
    const float* m = p + 4;
    const v8f k0 = xs * m[6] - m[0], k1 = xs * m[7] - m[1], k2 = xs * m[8] - m[2];
    const float l0 = py * m[6] - m[3], l1 = py * m[7] - m[4], l2 = py * m[8] - m[5];
    v8f pz = k0 * l1 - k1 * l0;
    const v8f pz_abs = pz < 0.f ? -pz : pz;
    pz = pz_abs < 1e-12f ? v8f{} + 1e-12f : pz;
    const v8f u = (k1 * l2 - k2 * l1) / pz, v = (k2 * l0 - k0 * l2) / pz;
    const v8f rho3d = u * u + v * v;
    const v8f rho2d = kSurfelFilter * (dx * dx + dy * dy);
    const v8i use3d = rho3d <= rho2d;
    const v8f rho = use3d ? rho3d : rho2d;
    const v8f depth = use3d ? u * m[6] + v * m[7] + m[8] : v8f{} + p[3];
    power = -0.5f * rho;
    inside = (rho <= kCutoff2) & (depth > 1e-2f);
  }
  v8f alpha = p[2] * exp8(power);
  alpha = alpha > kAlphaMax ? v8f{} + kAlphaMax : alpha;
  return (inside & (alpha >= kAlphaMin)) ? alpha : v8f{};
}

struct Entry {
  int64_t bin;  // gaussian * num_labels + label
  double value;
};

struct VoteView {
  int64_t width, height, tiles_x, K, num_labels;
  const float* params;
  const int32_t* spans;  // (M, 4) pixels [x0, x1) x [y0, y1) a splat can reach
  const int64_t *ids, *order, *offsets, *counts, *labels;
  float eps;       // a splat votes while T > eps; a pixel's walk ends once T <= eps
  float delta_sq;  // ... and only within delta px of its projected centre: delta squared once
                   // in double then rounded (as the PyTorch reference compares); +inf: no rule
};

// One 8x8 tile. The pixels still walking are the set bits of a 64-bit word; a tile's labels are
// a few bit masks (`slot_bits`), so a splat's votes per label are popcounts of one AND.
template <bool Surfel, bool Weighted, bool Avx2>
INLINE int64_t walk_tile(const VoteView& V, int64_t ti, std::vector<Entry>& out) {
  constexpr int tile = 8;
  const int32_t tx0 = static_cast<int32_t>((ti % V.tiles_x) * tile);
  const int32_t ty0 = static_cast<int32_t>((ti / V.tiles_x) * tile);
  v8f T[tile];
  int slot[64];
  uint64_t slot_bits[64] = {};
  int64_t slot_label[64];
  int slots = 0;
  uint64_t active = 0;
  for (int q = 0; q < 64; ++q) {
    const int64_t x = tx0 + q % tile, y = ty0 + q / tile;
    slot[q] = 0;
    if (x >= V.width || y >= V.height || !(1.f > V.eps)) continue;
    const int64_t lab = V.labels[y * V.width + x];
    int k = 0;
    while (k < slots && slot_label[k] != lab) ++k;
    if (k == slots) slot_label[slots++] = lab;
    slot[q] = k;
    slot_bits[k] |= uint64_t{1} << q;
    active |= uint64_t{1} << q;
  }
  for (int r = 0; r < tile; ++r) T[r] = v8f{} + 1.f;
  v8f xs;
  for (int l = 0; l < 8; ++l) xs[l] = static_cast<float>(tx0 + l) + 0.5f;
  const v8i lane_index = {0, 1, 2, 3, 4, 5, 6, 7};
  int64_t cast = 0;
  double weight[64];
  const int64_t n = V.counts[ti], base = V.offsets[ti];
  for (int64_t j = 0; j < n && active; ++j) {
    const int64_t s = V.order[base + j];
    const int32_t* span = V.spans + s * 4;
    const int x0 = std::max(span[0] - tx0, 0), x1 = std::min(span[1] - tx0, tile);
    const int y0 = std::max(span[2] - ty0, 0), y1 = std::min(span[3] - ty0, tile);
    if (x0 >= x1 || y0 >= y1) continue;
    const uint64_t row_span = ((uint64_t{1} << (x1 - x0)) - 1) << x0;
    const uint64_t rows = (y1 - y0 == tile ? ~uint64_t{0} : ((uint64_t{1} << (tile * (y1 - y0))) - 1))
                          << (tile * y0);
    if (!(row_span * 0x0101010101010101ull & rows & active)) continue;
    const float* p = V.params + s * V.K;
    uint64_t votes = 0;
    if constexpr (Weighted) std::fill(weight, weight + slots, 0.0);
    for (int ly = y0; ly < y1; ++ly) {
      const uint32_t live = static_cast<uint32_t>((active >> (ly * tile)) & row_span);
      if (!live) continue;
      const float py = static_cast<float>(ty0 + ly) + 0.5f;
      const v8f alpha = row_alpha<Surfel>(p, xs, py);
      const v8i in_span = ((v8i{} + static_cast<int32_t>(live)) >> lane_index) & 1;
      const v8i hit = (in_span != 0) & (alpha > 0.f);
      const v8f before = T[ly];
      const v8f after = hit ? before * (1.f - alpha) : before;
      T[ly] = after;
      v8i aligned = hit;
      if (V.delta_sq < std::numeric_limits<float>::infinity()) {
        const v8f dx = xs - p[0];
        const float dy = py - p[1];
        aligned &= (dx * dx + dy * dy) < V.delta_sq;
      }
      const uint32_t row_votes = lane_bits<Avx2>(aligned);
      const uint32_t ended = lane_bits<Avx2>(hit & ~(after > V.eps));
      active &= ~(static_cast<uint64_t>(ended) << (ly * tile));
      votes |= static_cast<uint64_t>(row_votes) << (ly * tile);
      if constexpr (Weighted) {
        const v8f w = alpha * before;
        for (uint32_t b = row_votes; b; b &= b - 1) {
          const int l = __builtin_ctz(b);
          weight[slot[ly * tile + l]] += static_cast<double>(w[l]);
        }
      }
    }
    if (!votes) continue;
    cast += __builtin_popcountll(votes);
    const int64_t first_bin = V.ids[s] * V.num_labels;
    for (int k = 0; k < slots; ++k) {
      const uint64_t mine = votes & slot_bits[k];
      if (!mine) continue;
      const double value = Weighted ? weight[k] : static_cast<double>(__builtin_popcountll(mine));
      out.push_back({first_bin + slot_label[k], value});
    }
  }
  return cast;
}

using WalkFn = int64_t (*)(const VoteView&, int64_t, std::vector<Entry>&);

template <bool Surfel, bool Weighted>
int64_t walk_generic(const VoteView& V, int64_t ti, std::vector<Entry>& out) {
  return walk_tile<Surfel, Weighted, false>(V, ti, out);
}

#if defined(__x86_64__) || defined(__i386__)
template <bool Surfel, bool Weighted>
__attribute__((target("avx2"))) int64_t walk_avx2(const VoteView& V, int64_t ti,
                                                   std::vector<Entry>& out) {
  return walk_tile<Surfel, Weighted, true>(V, ti, out);
}
#endif

// AVX2 where the processor has it (x86), else the baseline build; SAGONLINE_VOTE_SIMD=generic
// forces the baseline (the tests compare the two).
bool use_avx2() {
#if defined(__x86_64__) || defined(__i386__)
  const char* force = std::getenv("SAGONLINE_VOTE_SIMD");
  if (force != nullptr && std::string(force) == "generic") return false;
  return __builtin_cpu_supports("avx2");
#else
  return false;
#endif
}

WalkFn pick_walk(bool surfel, bool weighted) {
#if defined(__x86_64__) || defined(__i386__)
  if (use_avx2()) {
    if (surfel) return weighted ? walk_avx2<true, true> : walk_avx2<true, false>;
    return weighted ? walk_avx2<false, true> : walk_avx2<false, false>;
  }
#endif
  if (surfel) return weighted ? walk_generic<true, true> : walk_generic<true, false>;
  return weighted ? walk_generic<false, true> : walk_generic<false, false>;
}

}  // namespace

// Adds one view's votes into hist (N * num_labels, float64) and returns how many were cast.
// ids (M,): the Gaussian of each projected splat; labels (H * W,): the view's mask.
int64_t vote(bool surfel, torch::Tensor ids, torch::Tensor params, torch::Tensor spans,
             torch::Tensor order, torch::Tensor offsets, torch::Tensor counts, int64_t width,
             int64_t height, int64_t tile, torch::Tensor labels, int64_t num_labels, double eps,
             std::optional<double> delta, bool weighted, torch::Tensor hist) {
  params = params.contiguous();
  spans = spans.contiguous();
  TORCH_CHECK(spans.dtype() == torch::kInt32, "spans: int32");
  ids = ids.contiguous();
  labels = labels.contiguous();
  TORCH_CHECK(hist.is_contiguous() && hist.dtype() == torch::kFloat64, "hist: float64");
  TORCH_CHECK(ids.dtype() == torch::kInt64 && labels.dtype() == torch::kInt64, "ids, labels: int64");
  TORCH_CHECK(labels.numel() == width * height, "labels must hold one id per pixel");
  TORCH_CHECK(tile == 8, "the vote walks tiles of 8x8 pixels");
  TORCH_CHECK(params.dtype() == torch::kFloat32 && params.size(1) == (surfel ? 13 : 7),
              "packed splat parameters have the wrong type or width");
  const int64_t n_tiles = counts.size(0);
  // as the PyTorch path compares float32 distances with the double delta^2 cast to float32
  const VoteView V{width,
                   height,
                   (width + tile - 1) / tile,
                   params.size(1),
                   num_labels,
                   params.data_ptr<float>(),
                   spans.data_ptr<int32_t>(),
                   ids.data_ptr<int64_t>(),
                   order.data_ptr<int64_t>(),
                   offsets.data_ptr<int64_t>(),
                   counts.data_ptr<int64_t>(),
                   labels.data_ptr<int64_t>(),
                   static_cast<float>(eps),
                   delta ? static_cast<float>(*delta * *delta)
                         : std::numeric_limits<float>::infinity()};
  const WalkFn walk = pick_walk(surfel, weighted);
  std::vector<std::vector<Entry>> per_tile(n_tiles);
  std::vector<int64_t> cast(n_tiles, 0);
  for_each_tile(n_tiles, [&](int64_t ti) {
    if (V.counts[ti] > 0) cast[ti] = walk(V, ti, per_tile[ti]);
  });
  double* H = hist.data_ptr<double>();
  int64_t total = 0;
  for (int64_t ti = 0; ti < n_tiles; ++ti) {
    for (const Entry& e : per_tile[ti]) H[e.bin] += e.value;
    total += cast[ti];
  }
  return total;
}

std::string vote_simd() { return use_avx2() ? "avx2" : "generic"; }
