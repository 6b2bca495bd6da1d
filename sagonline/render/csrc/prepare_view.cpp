// The vote's projection, at the floor of the CPU: the no-grad twin of
// sagonline/render/projection.py `project` (same culling, same packed parameters
// [mx, my, opacity, depth, conic a b c | surfel transform M]) plus a stable radix sort by depth
// and the tile lists of `bin_tiles` (raster_cpu.cpp). Its boxes are tighter than the 3-sigma
// boxes: they bound where alpha >= 1/255, which depends on the opacity. The walk that votes
// over these lists is vote_cpu.cpp's.

#include <cstdint>
#include <cstring>
#include <limits>
#include <optional>
#include <vector>
#include "splat_common.h"

using namespace splat;

namespace {
struct Camera {
  float R[9], t[3], K[9], fx, fy, cx, cy;
  int64_t width, height;
  float near;
};

// Mahalanobis radius^2 inside which a splat of this opacity reaches alpha >= 1/255 (at most the
// 3-sigma support's 9; a 2e-3 margin keeps float rounding at the edge inside): boxes drawn with
// it list a faint splat only in the tiles it can change.
inline float reach2(float opacity) {
  return std::min(kCutoff2, 2.f * std::log(opacity / kAlphaMin) + 2e-3f);
}

// One 3DGS ellipsoid: packed params (7) and box (4); false where projection culls it.
bool project_ellipsoid(const Camera& c, const float* mean, const float* q, const float* scale,
                       float opacity, float* P, float* box) {
  float pc[3];
  for (int i = 0; i < 3; ++i)
    pc[i] = c.R[3 * i] * mean[0] + c.R[3 * i + 1] * mean[1] + c.R[3 * i + 2] * mean[2] + c.t[i];
  const float z = std::max(pc[2], 1e-6f);
  const float W = static_cast<float>(c.width), H = static_cast<float>(c.height);
  const float lim_xp = (W - c.cx) / c.fx + 0.3f * W / (2 * c.fx);
  const float lim_xn = c.cx / c.fx + 0.3f * W / (2 * c.fx);
  const float lim_yp = (H - c.cy) / c.fy + 0.3f * H / (2 * c.fy);
  const float lim_yn = c.cy / c.fy + 0.3f * H / (2 * c.fy);
  const float tx = std::clamp(pc[0] / z, -lim_xn, lim_xp) * z;
  const float ty = std::clamp(pc[1] / z, -lim_yn, lim_yp) * z;
  const float J[6] = {c.fx / z, 0.f, -c.fx * tx / (z * z), 0.f, c.fy / z, -c.fy * ty / (z * z)};
  const float w = q[0], x = q[1], y = q[2], zq = q[3];
  const float rot[9] = {1 - 2 * (y * y + zq * zq), 2 * (x * y - w * zq), 2 * (x * zq + w * y),
                        2 * (x * y + w * zq), 1 - 2 * (x * x + zq * zq), 2 * (y * zq - w * x),
                        2 * (x * zq - w * y), 2 * (y * zq + w * x), 1 - 2 * (x * x + y * y)};
  float M[9], T[6];  // M = R_cam rot S; T = J M: cov2d = T T^T
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j)
      M[3 * i + j] = (c.R[3 * i] * rot[j] + c.R[3 * i + 1] * rot[3 + j] +
                      c.R[3 * i + 2] * rot[6 + j]) * scale[j];
  for (int i = 0; i < 2; ++i)
    for (int j = 0; j < 3; ++j)
      T[3 * i + j] = J[3 * i] * M[j] + J[3 * i + 1] * M[3 + j] + J[3 * i + 2] * M[6 + j];
  const float a = T[0] * T[0] + T[1] * T[1] + T[2] * T[2] + 0.3f;
  const float b = T[0] * T[3] + T[1] * T[4] + T[2] * T[5];
  const float cc = T[3] * T[3] + T[4] * T[4] + T[5] * T[5] + 0.3f;
  const float det = a * cc - b * b;
  if (!(det > 0.f)) return false;
  const float mx = c.fx * pc[0] / z + c.cx, my = c.fy * pc[1] / z + c.cy;
  const float r2 = reach2(opacity);
  const float ex = std::sqrt(r2 * a), ey = std::sqrt(r2 * cc);
  const float P7[7] = {mx, my, opacity, pc[2], cc / det, -b / det, a / det};
  std::copy(P7, P7 + 7, P);
  box[0] = mx - ex;
  box[1] = mx + ex;
  box[2] = my - ey;
  box[3] = my + ey;
  return pc[2] > c.near;
}

// One 2DGS surfel: packed params (13) and box (4) from its homogeneous transform M = K [tu tv p].
bool project_surfel(const Camera& c, const float* mean, const float* q, const float* scale,
                    float opacity, float* P, float* box) {
  const float w = q[0], x = q[1], y = q[2], zq = q[3];
  const float rot[9] = {1 - 2 * (y * y + zq * zq), 2 * (x * y - w * zq), 2 * (x * zq + w * y),
                        2 * (x * y + w * zq), 1 - 2 * (x * x + zq * zq), 2 * (y * zq - w * x),
                        2 * (x * zq - w * y), 2 * (y * zq + w * x), 1 - 2 * (x * x + y * y)};
  float cols[3][3];  // camera-space tu, tv, centre
  for (int i = 0; i < 3; ++i) {
    cols[0][i] = c.R[3 * i] * rot[0] * scale[0] + c.R[3 * i + 1] * rot[3] * scale[0] +
                 c.R[3 * i + 2] * rot[6] * scale[0];
    cols[1][i] = c.R[3 * i] * rot[1] * scale[1] + c.R[3 * i + 1] * rot[4] * scale[1] +
                 c.R[3 * i + 2] * rot[7] * scale[1];
    cols[2][i] = c.R[3 * i] * mean[0] + c.R[3 * i + 1] * mean[1] + c.R[3 * i + 2] * mean[2] + c.t[i];
  }
  float M[9];  // row-major: M = K [tu tv p]
  for (int r = 0; r < 3; ++r)
    for (int j = 0; j < 3; ++j)
      M[3 * r + j] = c.K[3 * r] * cols[j][0] + c.K[3 * r + 1] * cols[j][1] + c.K[3 * r + 2] * cols[j][2];
  const float wz = M[8];
  const float mx = M[2] / std::max(wz, 1e-6f), my = M[5] / std::max(wz, 1e-6f);
  const float r2 = reach2(opacity);
  const float qd[3] = {r2, r2, -1.f};
  float D[9];  // D = M diag(9, 9, -1) M^T
  for (int r = 0; r < 3; ++r)
    for (int s = 0; s < 3; ++s)
      D[3 * r + s] = M[3 * r] * qd[0] * M[3 * s] + M[3 * r + 1] * qd[1] * M[3 * s + 1] +
                     M[3 * r + 2] * qd[2] * M[3 * s + 2];
  const float d22 = D[8];
  if (!(d22 < 0.f)) return false;
  const float ccx = D[2] / d22, ccy = D[5] / d22;
  const float hx = std::sqrt(std::max(D[2] * D[2] - D[0] * D[8], 0.f)) / std::fabs(d22);
  const float hy = std::sqrt(std::max(D[5] * D[5] - D[4] * D[8], 0.f)) / std::fabs(d22);
  const float rf = std::sqrt(r2 / kSurfelFilter);
  box[0] = std::min(ccx - hx, mx - rf);
  box[1] = std::max(ccx + hx, mx + rf);
  box[2] = std::min(ccy - hy, my - rf);
  box[3] = std::max(ccy + hy, my + rf);
  P[0] = mx;
  P[1] = my;
  P[2] = opacity;
  P[3] = cols[2][2];
  std::copy(M, M + 9, P + 4);
  return cols[2][2] > c.near;
}

// Stable LSD radix sort of positive float keys: the order torch.sort(stable=True) gives.
std::vector<int64_t> sort_by_depth(const float* depth, int64_t m) {
  std::vector<uint32_t> key(m), key2(m);
  std::vector<int64_t> idx(m), idx2(m);
  for (int64_t i = 0; i < m; ++i) {
    std::memcpy(&key[i], depth + i, 4);  // positive floats order as their bits
    idx[i] = i;
  }
  for (int shift = 0; shift < 32; shift += 8) {
    int64_t count[257] = {};
    for (int64_t i = 0; i < m; ++i) ++count[((key[i] >> shift) & 255) + 1];
    for (int b = 0; b < 256; ++b) count[b + 1] += count[b];
    for (int64_t i = 0; i < m; ++i) {
      const int64_t to = count[(key[i] >> shift) & 255]++;
      key2[to] = key[i];
      idx2[to] = idx[i];
    }
    key.swap(key2);
    idx.swap(idx2);
  }
  return idx;
}

}  // namespace

// Projects, culls, depth-sorts and bins one view's splats: ids (M,), params (M, 7 | 13),
// boxes (M, 4), spans (M, 4) int32 pixel ranges, order, offsets, counts (as bin_tiles).
std::vector<torch::Tensor> prepare_view(bool surfel, torch::Tensor means, torch::Tensor quats,
                                        torch::Tensor scales, torch::Tensor opacities,
                                        torch::Tensor rotation, torch::Tensor translation,
                                        torch::Tensor intrinsics, int64_t width, int64_t height,
                                        double near, int64_t tile) {
  for (auto* t : {&means, &quats, &scales, &opacities, &rotation, &translation, &intrinsics}) {
    TORCH_CHECK(t->dtype() == torch::kFloat32, "prepare_view: float32 inputs");
    *t = t->contiguous();
  }
  const int64_t n = means.size(0), K = surfel ? 13 : 7, S = scales.size(1);
  Camera c;
  std::memcpy(c.R, rotation.data_ptr<float>(), 9 * 4);
  std::memcpy(c.t, translation.data_ptr<float>(), 3 * 4);
  const float* Ki = intrinsics.data_ptr<float>();
  std::memcpy(c.K, Ki, 9 * 4);
  c.fx = Ki[0];
  c.fy = Ki[4];
  c.cx = Ki[2];
  c.cy = Ki[5];
  c.width = width;
  c.height = height;
  c.near = static_cast<float>(near);
  std::vector<float> all_params(n * K), all_boxes(n * 4);
  std::vector<char> keep(n, 0);
  const float *Mn = means.data_ptr<float>(), *Q = quats.data_ptr<float>();
  const float *Sc = scales.data_ptr<float>(), *O = opacities.data_ptr<float>();
  at::parallel_for(0, n, 2048, [&](int64_t begin, int64_t end) {
    for (int64_t i = begin; i < end; ++i) {
      float* P = all_params.data() + i * K;
      float* box = all_boxes.data() + i * 4;
      const bool ok = surfel ? project_surfel(c, Mn + 3 * i, Q + 4 * i, Sc + S * i, O[i], P, box)
                             : project_ellipsoid(c, Mn + 3 * i, Q + 4 * i, Sc + S * i, O[i], P, box);
      bool finite = true;
      for (int k = 0; k < 4; ++k) finite = finite && std::isfinite(box[k]);
      const bool on_screen = box[1] > 0.f && box[0] < width && box[3] > 0.f && box[2] < height;
      keep[i] = ok && finite && on_screen && O[i] >= kAlphaMin;
    }
  });
  int64_t m = 0;
  for (int64_t i = 0; i < n; ++i) m += keep[i];
  auto ids = torch::empty({m}, torch::kInt64);
  auto params = torch::empty({m, K}, torch::kFloat32);
  auto boxes = torch::empty({m, 4}, torch::kFloat32);
  auto spans = torch::empty({m, 4}, torch::kInt32);
  auto depth = std::vector<float>(m);
  int64_t* I = ids.data_ptr<int64_t>();
  float *P = params.data_ptr<float>(), *B = boxes.data_ptr<float>();
  int32_t* Sp = spans.data_ptr<int32_t>();
  // the pixels whose centre lies in the box, with a 0.01 px margin for rounding at its edge
  auto first = [](float v) {
    return static_cast<int32_t>(std::clamp(std::ceil(v - 0.5f - 0.01f), -1e9f, 1e9f));
  };
  auto past = [](float v) {
    return static_cast<int32_t>(std::clamp(std::floor(v - 0.5f + 0.01f), -1e9f, 1e9f)) + 1;
  };
  for (int64_t i = 0, o = 0; i < n; ++i) {
    if (!keep[i]) continue;
    I[o] = i;
    std::copy(all_params.begin() + i * K, all_params.begin() + (i + 1) * K, P + o * K);
    std::copy(all_boxes.begin() + i * 4, all_boxes.begin() + (i + 1) * 4, B + o * 4);
    depth[o] = P[o * K + 3];
    const float* b = B + o * 4;
    int32_t* sp = Sp + o * 4;
    sp[0] = first(b[0]);
    sp[1] = past(b[1]);
    sp[2] = first(b[2]);
    sp[3] = past(b[3]);
    ++o;
  }
  const std::vector<int64_t> by_depth = sort_by_depth(depth.data(), m);
  auto order_in = torch::from_blob(const_cast<int64_t*>(by_depth.data()), {m}, torch::kInt64);
  const int64_t ntx = (width + tile - 1) / tile, nty = (height + tile - 1) / tile;
  auto lists = bin_tiles(boxes, order_in, ntx, nty, tile);
  return {ids, params, boxes, spans, lists[0], lists[1], lists[2]};
}
