// Default surfel frames of per-pixel Gaussians (the optional compiled path of
// drivingscene.gaussians.assembly.surfel_frames).
//
// One pass per image row instead of ~100 full-image tensor operations: back-project, normal from
// the smaller-step finite differences, the EWA footprint covariance in the tangent plane, its
// closed-form eigen-decomposition, the capped scales and the axis-frame quaternion, vectorised over
// the row's pixels. The arithmetic follows the torch path step by step (float32); the result is
// the same Gaussian up to float rounding (the tests compare covariances). Not differentiable: both
// callers pass detached depth.
#include <ATen/ATen.h>
#include <ATen/Parallel.h>
#include <torch/library.h>

#include <algorithm>
#include <cmath>
#include <vector>

namespace {

struct Camera {
  float fx, fy, cx, cy, skew;
};

// The surfel frames of one image row, every column at once, written without branches so that the
// compiler vectorises the column loop (-fno-math-errno -fno-trapping-math; the arithmetic and its
// order are those of the torch path's steps, IEEE float32, no FMA): the quaternion
// (w, x, y, z, each [width]), the two tangent scales before their logarithm and the pixel
// footprint in metres (log_scale[2] = log(thickness * pixel)).
struct RowOut {
  std::vector<float> qw, qx, qy, qz, s_small, s_large, pixel;
  std::vector<float> hx, hy, hz, ax, ay, az, bx, by, bz;  // camera points: this row (padded), above, below
  explicit RowOut(int64_t width)
      : qw(width), qx(width), qy(width), qz(width), s_small(width), s_large(width), pixel(width), hx(width + 2),
        hy(width + 2), hz(width + 2), ax(width), ay(width), az(width), bx(width), by(width), bz(width) {}
};

// Camera points of image row `row` (clamped to the image) into x, y, z: the depth (at least 1e-3)
// along the pixel's ray.
inline void row_points(const float* depth, const Camera& k, int64_t height, int64_t width, int64_t row, float* x, float* y,
                       float* z) {
  const int64_t r = std::min(std::max<int64_t>(row, 0), height - 1);
  const float* d = depth + r * width;
  const float ry = (static_cast<float>(r) - k.cy) / k.fy;
#pragma omp simd
  for (int64_t col = 0; col < width; ++col) {
    const float dc = std::max(d[col], 1e-3f);
    const float rx = (static_cast<float>(col) - k.cx - k.skew * ry) / k.fx;
    x[col] = rx * dc;
    y[col] = ry * dc;
    z[col] = dc;
  }
}

void surfel_row(const float* depth, const Camera& k, int64_t height, int64_t width, int64_t row, float footprint,
                float min_cos, RowOut& o) {
  row_points(depth, k, height, width, row, o.hx.data() + 1, o.hy.data() + 1, o.hz.data() + 1);
  o.hx[0] = o.hx[1], o.hy[0] = o.hy[1], o.hz[0] = o.hz[1];  // columns clamped at the border
  o.hx[width + 1] = o.hx[width], o.hy[width + 1] = o.hy[width], o.hz[width + 1] = o.hz[width];
  row_points(depth, k, height, width, row - 1, o.ax.data(), o.ay.data(), o.az.data());
  row_points(depth, k, height, width, row + 1, o.bx.data(), o.by.data(), o.bz.data());
  const float* hx = o.hx.data();
  const float* hy = o.hy.data();
  const float* hz = o.hz.data();
  const float f2 = footprint * footprint;
#pragma omp simd
  for (int64_t col = 0; col < width; ++col) {
    const float px = hx[col + 1], py = hy[col + 1], pz = hz[col + 1];
    // the finite differences with the smaller depth change (smaller_step)
    const float fx0 = hx[col + 2] - px, fy0 = hy[col + 2] - py, fz0 = hz[col + 2] - pz;
    const float bx0 = px - hx[col], by0 = py - hy[col], bz0 = pz - hz[col];
    const bool fwd_x = (std::fabs(fz0) <= std::fabs(bz0) && (std::fabs(fx0) + std::fabs(fy0) + std::fabs(fz0)) > 0) ||
                       (std::fabs(bx0) + std::fabs(by0) + std::fabs(bz0)) == 0;
    const float dxx = fwd_x ? fx0 : bx0, dxy = fwd_x ? fy0 : by0, dxz = fwd_x ? fz0 : bz0;
    const float fx1 = o.bx[col] - px, fy1 = o.by[col] - py, fz1 = o.bz[col] - pz;
    const float bx1 = px - o.ax[col], by1 = py - o.ay[col], bz1 = pz - o.az[col];
    const bool fwd_y = (std::fabs(fz1) <= std::fabs(bz1) && (std::fabs(fx1) + std::fabs(fy1) + std::fabs(fz1)) > 0) ||
                       (std::fabs(bx1) + std::fabs(by1) + std::fabs(bz1)) == 0;
    const float dyx = fwd_y ? fx1 : bx1, dyy = fwd_y ? fy1 : by1, dyz = fwd_y ? fz1 : bz1;
    // normal = normalize(cross(dx, dy)), facing the camera
    float nx = dxy * dyz - dxz * dyy, ny = dxz * dyx - dxx * dyz, nz = dxx * dyy - dxy * dyx;
    float inv = 1.0f / std::max(std::sqrt(nx * nx + ny * ny + nz * nz), 1e-12f);
    nx = nx * inv, ny = ny * inv, nz = nz * inv;
    const float flip = (nx * px + ny * py + nz * pz) > 0 ? -1.0f : 1.0f;
    nx = nx * flip, ny = ny * flip, nz = nz * flip;
    // tangent frame
    const bool use_x = std::fabs(nx) < 0.9f;
    const float gx = use_x ? 1.0f : 0.0f, gy = use_x ? 0.0f : 1.0f, gz = 0.0f;
    const float nh = nx * gx + ny * gy + nz * gz;
    float t1x = gx - nx * nh, t1y = gy - ny * nh, t1z = gz - nz * nh;
    inv = 1.0f / std::max(std::sqrt(t1x * t1x + t1y * t1y + t1z * t1z), 1e-12f);
    t1x = t1x * inv, t1y = t1y * inv, t1z = t1z * inv;
    const float t2x = ny * t1z - nz * t1y, t2y = nz * t1x - nx * t1z, t2z = nx * t1y - ny * t1x;
    // the EWA footprint in the tangent plane and its eigen-decomposition
    const float z = pz;
    const float j0x = k.fx / z, j0z = -k.fx * px / (z * z);
    const float j1y = k.fy / z, j1z = -k.fy * py / (z * z);
    const float a00 = j0x * t1x + 0.0f * t1y + j0z * t1z, a01 = j0x * t2x + 0.0f * t2y + j0z * t2z;
    const float a10 = 0.0f * t1x + j1y * t1y + j1z * t1z, a11 = 0.0f * t2x + j1y * t2y + j1z * t2z;
    float det = a00 * a11 - a01 * a10;
    det = std::fabs(det) < 1e-12f ? 1e-12f : det;
    const float i00 = a11 / det, i01 = -a01 / det, i10 = -a10 / det, i11 = a00 / det;
    const float a = f2 * (i00 * i00 + i01 * i01);
    const float b = f2 * (i00 * i10 + i01 * i11);
    const float c = f2 * (i10 * i10 + i11 * i11);
    const float half_gap = std::sqrt(((a - c) / 2) * ((a - c) / 2) + b * b);
    const float lam_large = (a + c) / 2 + half_gap;
    const float lam_small = f2 * f2 / (det * det * lam_large);
    const float r = 2 * half_gap;
    const float cos2 = (a - c) / r, sin2 = 2 * b / r;
    const float cos_p = std::sqrt((1 + cos2) / 2);
    const float sin_p = sin2 / (2 * cos_p);
    const float sin_n = std::copysign(std::sqrt((1 - cos2) / 2), sin2);
    const float cos_n = std::fabs(sin2) / (2 * std::fabs(sin_n));
    const float cos_phi = r > 0 ? (cos2 >= 0 ? cos_p : cos_n) : 1.0f;
    const float sin_phi = r > 0 ? (cos2 >= 0 ? sin_p : sin_n) : 0.0f;
    const float pixel = footprint * z / (0.5f * (k.fx + k.fy));
    const float cap = pixel / min_cos;
    o.s_small[col] = std::min(std::sqrt(std::max(lam_small, 1e-12f)), cap);
    o.s_large[col] = std::min(std::sqrt(std::max(lam_large, 1e-12f)), cap);
    o.pixel[col] = pixel;
    // the axis frame [d1 d2 n] (columns; d1 the large axis) to a quaternion
    float d1x = t1x * -sin_phi + t2x * cos_phi, d1y = t1y * -sin_phi + t2y * cos_phi, d1z = t1z * -sin_phi + t2z * cos_phi;
    inv = 1.0f / std::max(std::sqrt(d1x * d1x + d1y * d1y + d1z * d1z), 1e-12f);
    d1x = d1x * inv, d1y = d1y * inv, d1z = d1z * inv;
    const float d2x = ny * d1z - nz * d1y, d2y = nz * d1x - nx * d1z, d2z = nx * d1y - ny * d1x;
    // of the four frames equal up to flipping two axes, the first with the largest trace
    const float tr0 = d1x * 1.0f + d2y * 1.0f + nz * 1.0f;
    const float tr1 = d1x * 1.0f + d2y * -1.0f + nz * -1.0f;
    const float tr2 = d1x * -1.0f + d2y * 1.0f + nz * -1.0f;
    const float tr3 = d1x * -1.0f + d2y * -1.0f + nz * 1.0f;
    float s0 = 1.0f, s1 = 1.0f, s2 = 1.0f, best = tr0;
    const bool b1 = tr1 > best;
    best = b1 ? tr1 : best, s0 = b1 ? 1.0f : s0, s1 = b1 ? -1.0f : s1, s2 = b1 ? -1.0f : s2;
    const bool b2 = tr2 > best;
    best = b2 ? tr2 : best, s0 = b2 ? -1.0f : s0, s1 = b2 ? 1.0f : s1, s2 = b2 ? -1.0f : s2;
    const bool b3 = tr3 > best;
    s0 = b3 ? -1.0f : s0, s1 = b3 ? -1.0f : s1, s2 = b3 ? 1.0f : s2;
    const float c0x = d1x * s0, c0y = d1y * s0, c0z = d1z * s0;
    const float c1x = d2x * s1, c1y = d2y * s1, c1z = d2z * s1;
    const float c2x = nx * s2, c2y = ny * s2, c2z = nz * s2;
    const float w = 0.5f * std::sqrt(std::max(1.0f + c0x + c1y + c2z, 1e-12f));
    const float inv_4w = 1.0f / (4 * w);
    o.qw[col] = w;
    o.qx[col] = (c1z - c2y) * inv_4w;
    o.qy[col] = (c2x - c0z) * inv_4w;
    o.qz[col] = (c0y - c1x) * inv_4w;
  }
}

// Runs body(v, row, o) for the image rows [begin, end) of views x height rows, with `o` holding
// the row's surfel frames (`surfel_row`); one row buffer per call (per thread).
template <typename Body>
void for_surfel_rows(const float* depth, const float* intrinsics, int64_t height, int64_t width, float footprint,
                     float min_cos, int64_t begin, int64_t end, Body body) {
  RowOut o(width);
  for (int64_t vr = begin; vr < end; ++vr) {
    const int64_t v = vr / height, row = vr % height;
    const float* k9 = intrinsics + 9 * v;
    const Camera cam{k9[0], k9[4], k9[2], k9[5], k9[1]};
    surfel_row(depth + v * height * width, cam, height, width, row, footprint, min_cos, o);
    body(v, row, o);
  }
}

// The surfel's log scales at column `col` of a row: the two tangent axes and the thickness.
inline void surfel_log_scales(const RowOut& o, int64_t col, float thickness, float* out) {
  out[0] = std::log(o.s_small[col]);
  out[1] = std::log(o.s_large[col]);
  out[2] = std::log(thickness * o.pixel[col]);
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
    for_surfel_rows(d, kk, height, width, fp, mc, begin, end, [&](int64_t v, int64_t row, const RowOut& o) {
      for (int64_t col = 0; col < width; ++col) {
        const int64_t i = (v * height + row) * width + col;
        q[4 * i] = o.qw[col], q[4 * i + 1] = o.qx[col], q[4 * i + 2] = o.qy[col], q[4 * i + 3] = o.qz[col];
        surfel_log_scales(o, col, th, s + 3 * i);
      }
    });
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
    for_surfel_rows(d, kk, height, width, fp, mc, begin, end, [&](int64_t v, int64_t row, const RowOut& o) {
      for (int64_t col = 0; col < width; ++col) {
        const int64_t i = (v * height + row) * width + col;
        const float base_q[4] = {o.qw[col], o.qx[col], o.qy[col], o.qz[col]};
        float base_s[3];
        surfel_log_scales(o, col, th, base_s);
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
    });
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
