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
  const float inv = 1.0f / std::max(std::sqrt(dot(a, a)), 1e-12f);
  return {a.x * inv, a.y * inv, a.z * inv};
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
  // phi = atan2(2b, a - c) / 2, the direction of the large axis: its cosine and sine from the
  // double angle's by the half-angle formulas, the one without cancellation first (no trig calls).
  float cos_phi = 1.0f, sin_phi = 0.0f;
  const float r = 2 * half_gap;
  if (r > 0) {
    const float cos2 = (a - c) / r, sin2 = 2 * b / r;
    if (cos2 >= 0) {
      cos_phi = std::sqrt((1 + cos2) / 2);
      sin_phi = sin2 / (2 * cos_phi);
    } else {
      sin_phi = std::copysign(std::sqrt((1 - cos2) / 2), sin2);
      cos_phi = std::fabs(sin2) / (2 * std::fabs(sin_phi));
    }
  }
  const float pixel = footprint * z / (0.5f * (k.fx + k.fy));
  const float cap = pixel / min_cos;
  const float s_small = std::min(std::sqrt(std::max(lam_small, 1e-12f)), cap);
  const float s_large = std::min(std::sqrt(std::max(lam_large, 1e-12f)), cap);
  const Vec3 d1 = normalize(add(scale(t1, -sin_phi), scale(t2, cos_phi)));
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
  const float inv_4w = 1.0f / (4 * w);
  quat[1] = (c1.z - c2.y) * inv_4w;
  quat[2] = (c2.x - c0.z) * inv_4w;
  quat[3] = (c0.y - c1.x) * inv_4w;
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

// tanh through one exp (glibc's tanhf is several times slower; the same value up to ~1 ulp of 1)
inline float fast_tanh(float x) {
  const float e = std::exp(-2.0f * std::fabs(x));
  return std::copysign((1.0f - e) / (1.0f + e), x);
}

// The Gaussian head's activation at inference (the optional compiled path of
// drivingscene.models.gaussian_head.GaussianHead.activate, no gradients), in the same pass as the
// surfel frame it modifies:
//   log_scale = surfel log scale + 2 tanh(raw[0:3] / 2)
//   quat      = surfel quat * normalize((1, 0, 0, 0) + raw[3:7])
//   opacity   = raw[7] + opacity_bias
//   sh[0]     = (pixel RGB + 0.5 tanh(raw[8:11]) - 0.5) / sh_c0,  sh[1:] = raw[11:]
std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor> activate_surfels(
    const at::Tensor& depth_in, const at::Tensor& intrinsics_in, const at::Tensor& raw_in, const at::Tensor& images_in,
    double footprint, double thickness, double min_cos, double opacity_bias, double sh_c0) {
  TORCH_CHECK(depth_in.dim() == 3, "activate_surfels: depth must be [B, H, W]");
  const int64_t views = depth_in.size(0), height = depth_in.size(1), width = depth_in.size(2);
  TORCH_CHECK(intrinsics_in.dim() == 3 && intrinsics_in.size(0) == views, "activate_surfels: intrinsics must be [B, 3, 3]");
  TORCH_CHECK(raw_in.dim() == 4 && raw_in.size(0) == views && raw_in.size(1) == height && raw_in.size(2) == width &&
                  raw_in.size(3) >= 11 && (raw_in.size(3) - 11) % 3 == 0,
              "activate_surfels: raw must be [B, H, W, 8 + 3K]");
  TORCH_CHECK(images_in.dim() == 4 && images_in.size(0) == views && images_in.size(1) == 3 && images_in.size(2) == height &&
                  images_in.size(3) == width,
              "activate_surfels: images must be [B, 3, H, W]");
  const at::Tensor depth = depth_in.to(at::kFloat).contiguous();
  const at::Tensor intrinsics = intrinsics_in.to(at::kFloat).contiguous();
  const at::Tensor raw = raw_in.to(at::kFloat).contiguous();
  const at::Tensor images = images_in.to(at::kFloat).contiguous();
  const int64_t channels = raw.size(3), coeffs = (channels - 8) / 3, pixels = height * width;
  at::Tensor log_scales = at::empty({views, height, width, 3}, depth.options());
  at::Tensor quats = at::empty({views, height, width, 4}, depth.options());
  at::Tensor opacity = at::empty({views, height, width}, depth.options());
  at::Tensor sh = at::empty({views, height, width, coeffs, 3}, depth.options());
  const float* d = depth.data_ptr<float>();
  const float* kk = intrinsics.data_ptr<float>();
  const float* r = raw.data_ptr<float>();
  const float* img = images.data_ptr<float>();
  float* ls = log_scales.data_ptr<float>();
  float* q = quats.data_ptr<float>();
  float* op = opacity.data_ptr<float>();
  float* out_sh = sh.data_ptr<float>();
  const float fp = static_cast<float>(footprint), th = static_cast<float>(thickness), mc = static_cast<float>(min_cos);
  const float bias = static_cast<float>(opacity_bias), inv_c0 = static_cast<float>(1.0 / sh_c0);
  at::parallel_for(0, views * height, 16, [&](int64_t begin, int64_t end) {
    for (int64_t vr = begin; vr < end; ++vr) {
      const int64_t v = vr / height, row = vr % height;
      const float* k9 = kk + 9 * v;
      const Camera cam{k9[0], k9[4], k9[2], k9[5], k9[1]};
      const float* dv = d + v * pixels;
      for (int64_t col = 0; col < width; ++col) {
        const int64_t i = vr * width + col;
        float base_q[4], base_s[3];
        surfel_pixel(dv, cam, height, width, row, col, fp, th, mc, base_q, base_s);
        const float* x = r + channels * i;
        for (int j = 0; j < 3; ++j) ls[3 * i + j] = base_s[j] + 2.0f * fast_tanh(x[j] / 2.0f);
        // normalize((1, 0, 0, 0) + raw[3:7]) as F.normalize: divided by max(norm, 1e-12)
        const float w2 = 1.0f + x[3], x2 = x[4], y2 = x[5], z2 = x[6];
        const float inv = 1.0f / std::max(std::sqrt(w2 * w2 + x2 * x2 + y2 * y2 + z2 * z2), 1e-12f);
        const float dw = w2 * inv, dx = x2 * inv, dy = y2 * inv, dz = z2 * inv;
        const float w1 = base_q[0], x1 = base_q[1], y1 = base_q[2], z1 = base_q[3];
        q[4 * i + 0] = w1 * dw - x1 * dx - y1 * dy - z1 * dz;
        q[4 * i + 1] = w1 * dx + x1 * dw + y1 * dz - z1 * dy;
        q[4 * i + 2] = w1 * dy - x1 * dz + y1 * dw + z1 * dx;
        q[4 * i + 3] = w1 * dz + x1 * dy - y1 * dx + z1 * dw;
        op[i] = x[7] + bias;
        float* shi = out_sh + coeffs * 3 * i;
        const int64_t pixel = row * width + col;
        for (int j = 0; j < 3; ++j) {
          const float rgb = img[(v * 3 + j) * pixels + pixel] + 0.5f * fast_tanh(x[8 + j]);
          shi[j] = (rgb - 0.5f) * inv_c0;
        }
        for (int64_t j = 3; j < 3 * coeffs; ++j) shi[j] = x[8 + j];
      }
    }
  });
  return {log_scales, quats, opacity, sh};
}

}  // namespace

TORCH_LIBRARY_FRAGMENT(drivingscene_render, m) {
  m.def("surfel_frames(Tensor depth, Tensor intrinsics, float footprint, float thickness, float min_cos) -> (Tensor, Tensor)",
        &surfel_frames);
  m.def("activate_surfels(Tensor depth, Tensor intrinsics, Tensor raw, Tensor images, float footprint, float thickness, "
        "float min_cos, float opacity_bias, float sh_c0) -> (Tensor, Tensor, Tensor, Tensor)",
        &activate_surfels);
}
