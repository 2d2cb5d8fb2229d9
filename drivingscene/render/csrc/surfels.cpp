// Default surfel frames of per-pixel Gaussians (the optional compiled path of
// drivingscene.gaussians.assembly.surfel_frames).
//
// One pass per pixel instead of ~100 full-image tensor operations: back-project, normal from the
// smaller-step finite differences, the EWA footprint covariance in the tangent plane, its closed-form
// eigen-decomposition, the capped scales and the axis-frame quaternion. The arithmetic follows the
// torch path step by step (float32); the result is the same Gaussian up to float rounding (the
// tests compare covariances). Not differentiable: both callers pass detached depth.
#include <ATen/ATen.h>
#include <ATen/Parallel.h>
#include <torch/library.h>

#include <algorithm>
#include <cmath>

namespace {

struct Vec3 {
  float x, y, z;
};

inline Vec3 sub(Vec3 a, Vec3 b) { return {a.x - b.x, a.y - b.y, a.z - b.z}; }
inline Vec3 scale(Vec3 a, float s) { return {a.x * s, a.y * s, a.z * s}; }
inline Vec3 add(Vec3 a, Vec3 b) { return {a.x + b.x, a.y + b.y, a.z + b.z}; }
inline float dot(Vec3 a, Vec3 b) { return a.x * b.x + a.y * b.y + a.z * b.z; }
inline Vec3 cross(Vec3 a, Vec3 b) { return {a.y * b.z - a.z * b.y, a.z * b.x - a.x * b.z, a.x * b.y - a.y * b.x}; }
inline Vec3 normalize(Vec3 a) {  // F.normalize: a / max(|a|, 1e-12)
  const float n = std::max(std::sqrt(dot(a, a)), 1e-12f);
  return {a.x / n, a.y / n, a.z / n};
}
inline float abs_sum(Vec3 a) { return std::fabs(a.x) + std::fabs(a.y) + std::fabs(a.z); }

// The finite difference with the smaller depth change (it does not cross a depth edge).
inline Vec3 smaller_step(Vec3 forward, Vec3 backward) {
  bool use_forward = std::fabs(forward.z) <= std::fabs(backward.z);
  use_forward = (use_forward && abs_sum(forward) > 0) || abs_sum(backward) == 0;
  return use_forward ? forward : backward;
}

struct Camera {
  float fx, fy, cx, cy, skew;
};

inline Vec3 point_at(const float* depth, const Camera& k, int64_t width, int64_t row, int64_t col) {
  const float d = std::max(depth[row * width + col], 1e-3f);
  const float y = (static_cast<float>(row) - k.cy) / k.fy;
  const float x = (static_cast<float>(col) - k.cx - k.skew * y) / k.fx;
  return {x * d, y * d, d};
}

void surfel_pixel(const float* depth, const Camera& k, int64_t height, int64_t width, int64_t row, int64_t col,
                  float footprint, float thickness, float min_cos, float* quat, float* log_scale) {
  const Vec3 p = point_at(depth, k, width, row, col);
  const Vec3 right = point_at(depth, k, width, row, std::min(col + 1, width - 1));
  const Vec3 left = point_at(depth, k, width, row, std::max<int64_t>(col - 1, 0));
  const Vec3 down = point_at(depth, k, width, std::min(row + 1, height - 1), col);
  const Vec3 up = point_at(depth, k, width, std::max<int64_t>(row - 1, 0), col);
  const Vec3 dx = smaller_step(sub(right, p), sub(p, left));
  const Vec3 dy = smaller_step(sub(down, p), sub(p, up));
  Vec3 n = normalize(cross(dx, dy));
  if (dot(n, p) > 0) n = scale(n, -1.0f);

  const Vec3 helper = std::fabs(n.x) < 0.9f ? Vec3{1, 0, 0} : Vec3{0, 1, 0};
  const Vec3 t1 = normalize(sub(helper, scale(n, dot(n, helper))));
  const Vec3 t2 = cross(n, t1);

  const float z = p.z;
  const Vec3 j0 = {k.fx / z, 0.0f, -k.fx * p.x / (z * z)};
  const Vec3 j1 = {0.0f, k.fy / z, -k.fy * p.y / (z * z)};
  const float a00 = dot(j0, t1), a01 = dot(j0, t2), a10 = dot(j1, t1), a11 = dot(j1, t2);
  float det = a00 * a11 - a01 * a10;
  if (std::fabs(det) < 1e-12f) det = 1e-12f;
  const float i00 = a11 / det, i01 = -a01 / det, i10 = -a10 / det, i11 = a00 / det;
  const float f2 = footprint * footprint;
  const float a = f2 * (i00 * i00 + i01 * i01);
  const float b = f2 * (i00 * i10 + i01 * i11);
  const float c = f2 * (i10 * i10 + i11 * i11);
  const float half_gap = std::sqrt(((a - c) / 2) * ((a - c) / 2) + b * b);
  const float lam_large = (a + c) / 2 + half_gap;
  const float lam_small = f2 * f2 / (det * det * lam_large);  // stable, unlike (a + c) / 2 - half_gap
  const float phi = 0.5f * std::atan2(2 * b, a - c);
  const float pixel = footprint * z / (0.5f * (k.fx + k.fy));
  const float cap = pixel / min_cos;
  const float s_small = std::min(std::sqrt(std::max(lam_small, 1e-12f)), cap);
  const float s_large = std::min(std::sqrt(std::max(lam_large, 1e-12f)), cap);
  const Vec3 d1 = normalize(add(scale(t1, -std::sin(phi)), scale(t2, std::cos(phi))));
  const Vec3 d2 = cross(n, d1);
  log_scale[0] = std::log(s_small);
  log_scale[1] = std::log(s_large);
  log_scale[2] = std::log(thickness * pixel);

  // Axis frame [d1 d2 n] (columns) to a quaternion: of the four frames equal up to flipping two
  // axes, the one with the largest trace, then the trace formula (as axes_to_quat).
  static const float flips[4][3] = {{1, 1, 1}, {1, -1, -1}, {-1, 1, -1}, {-1, -1, 1}};
  const float diag[3] = {d1.x, d2.y, n.z};
  int best = 0;
  float best_trace = -1e30f;
  for (int f = 0; f < 4; ++f) {
    const float tr = diag[0] * flips[f][0] + diag[1] * flips[f][1] + diag[2] * flips[f][2];
    if (tr > best_trace) {
      best_trace = tr;
      best = f;
    }
  }
  const Vec3 c0 = scale(d1, flips[best][0]), c1 = scale(d2, flips[best][1]), c2 = scale(n, flips[best][2]);
  // r[i][j] is component i of column j.
  const float w = 0.5f * std::sqrt(std::max(1.0f + c0.x + c1.y + c2.z, 1e-12f));
  quat[0] = w;
  quat[1] = (c1.z - c2.y) / (4 * w);
  quat[2] = (c2.x - c0.z) / (4 * w);
  quat[3] = (c0.y - c1.x) / (4 * w);
}

std::tuple<at::Tensor, at::Tensor> surfel_frames(const at::Tensor& depth_in, const at::Tensor& intrinsics_in,
                                                 double footprint, double thickness, double min_cos) {
  TORCH_CHECK(depth_in.dim() == 3, "surfel_frames: depth must be [V, H, W]");
  TORCH_CHECK(intrinsics_in.dim() == 3 && intrinsics_in.size(0) == depth_in.size(0), "surfel_frames: intrinsics must be [V, 3, 3]");
  TORCH_CHECK(depth_in.device().is_cpu(), "surfel_frames: CPU tensors only");
  const at::Tensor depth = depth_in.to(at::kFloat).contiguous();
  const at::Tensor intrinsics = intrinsics_in.to(at::kFloat).contiguous();
  const int64_t views = depth.size(0), height = depth.size(1), width = depth.size(2);
  at::Tensor quats = at::empty({views, height, width, 4}, depth.options());
  at::Tensor log_scales = at::empty({views, height, width, 3}, depth.options());
  const float* d = depth.data_ptr<float>();
  const float* kk = intrinsics.data_ptr<float>();
  float* q = quats.data_ptr<float>();
  float* s = log_scales.data_ptr<float>();
  const float fp = static_cast<float>(footprint), th = static_cast<float>(thickness), mc = static_cast<float>(min_cos);
  at::parallel_for(0, views * height, 16, [&](int64_t begin, int64_t end) {
    for (int64_t vr = begin; vr < end; ++vr) {
      const int64_t v = vr / height, row = vr % height;
      const float* k9 = kk + 9 * v;
      const Camera cam{k9[0], k9[4], k9[2], k9[5], k9[1]};
      const float* dv = d + v * height * width;
      for (int64_t col = 0; col < width; ++col) {
        const int64_t i = vr * width + col;
        surfel_pixel(dv, cam, height, width, row, col, fp, th, mc, q + 4 * i, s + 3 * i);
      }
    }
  });
  return {quats, log_scales};
}

}  // namespace

TORCH_LIBRARY_FRAGMENT(drivingscene_render, m) {
  m.def("surfel_frames(Tensor depth, Tensor intrinsics, float footprint, float thickness, float min_cos) -> (Tensor, Tensor)",
        &surfel_frames);
}
