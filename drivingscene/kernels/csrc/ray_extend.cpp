// Per-pixel Gaussians' footprints: the footprint rule (the optional compiled path of
// drivingscene.gaussians.assembly.pixel_footprints) and the extension along the view rays (of
// drivingscene.gaussians.assembly.extend_along_rays_torch).
//
// The footprint rule follows the torch path's float32 arithmetic, one pass per image row (the
// torch path runs some sixty element-wise operations over every pixel's maps).
//
// Each Gaussian's covariance R S^2 R^T, in its source camera's axes, gains the variance sigma^2
// along the unit ray from the camera centre to its mean, and the sum is decomposed again into a
// rotation and three scales: a closed-form eigen-decomposition of the symmetric 3x3 in double
// precision, per Gaussian (torch's batched eigh costs ~1 s for 340k of them on two cores). The
// result is the same covariance as the torch path up to float rounding (the tests compare
// covariances: eigenvector order and signs are arbitrary). Not differentiable.
#include <ATen/ATen.h>
#include <ATen/Parallel.h>
#include <torch/library.h>

#include <algorithm>
#include <cmath>

namespace {

// Eigen-decomposition of the symmetric a (row-major 3x3): eigenvalues in `values`, eigenvectors
// as the columns of v (row-major), in closed form. The eigenvalues of the scaled, shifted matrix
// come from the trigonometric solution of its characteristic cubic; the eigenvector of the one
// farthest from the other two (the largest where the cubic's half determinant is >= 0, else the
// smallest) is the largest cross product of two rows of a - lambda I; the other two are the exact
// 2x2 rotation of the plane orthogonal to it (one Jacobi rotation), so that two equal eigenvalues
// cost no accuracy. Each eigenvalue is then the matrix's Rayleigh quotient on its vector. The
// whole extension took 0.69x of its time with cyclic Jacobi sweeps (docs/performance.md), with the
// same covariances up to double rounding.
void eigen3(const double a[9], double values[3], double v[9]) {
  double scale = 0.0;
  for (int i = 0; i < 9; ++i) scale = std::max(scale, std::fabs(a[i]));
  for (int i = 0; i < 9; ++i) v[i] = (i % 4 == 0) ? 1.0 : 0.0;
  if (!(scale > 0.0)) {
    values[0] = values[1] = values[2] = 0.0;
    return;
  }
  double m[9];
  for (int i = 0; i < 9; ++i) m[i] = a[i] / scale;
  const double q = (m[0] + m[4] + m[8]) / 3.0;
  const double b00 = m[0] - q, b11 = m[4] - q, b22 = m[8] - q, b01 = m[1], b02 = m[2], b12 = m[5];
  const double p2 = (b00 * b00 + b11 * b11 + b22 * b22 + 2.0 * (b01 * b01 + b02 * b02 + b12 * b12)) / 6.0;
  if (p2 < 1e-30) {  // a multiple of the identity up to rounding: any axes
    values[0] = a[0], values[1] = a[4], values[2] = a[8];
    return;
  }
  const double p = std::sqrt(p2);
  const double det = b00 * (b11 * b22 - b12 * b12) - b01 * (b01 * b22 - b12 * b02) + b02 * (b01 * b12 - b11 * b02);
  const double half = std::min(1.0, std::max(-1.0, det / (2.0 * p2 * p)));
  const double phi = std::acos(half) / 3.0;
  const double lambda = q + 2.0 * p * (half >= 0.0 ? std::cos(phi) : std::cos(phi + 2.0943951023931957));
  // its eigenvector: the largest cross product of two rows of m - lambda I
  const double r[3][3] = {{m[0] - lambda, m[1], m[2]}, {m[3], m[4] - lambda, m[5]}, {m[6], m[7], m[8] - lambda}};
  double best[3] = {1.0, 0.0, 0.0}, best_norm = 0.0;
  for (int i = 0; i < 2; ++i) {
    for (int j = i + 1; j < 3; ++j) {
      const double c[3] = {r[i][1] * r[j][2] - r[i][2] * r[j][1], r[i][2] * r[j][0] - r[i][0] * r[j][2],
                           r[i][0] * r[j][1] - r[i][1] * r[j][0]};
      const double n = c[0] * c[0] + c[1] * c[1] + c[2] * c[2];
      if (n > best_norm) best_norm = n, best[0] = c[0], best[1] = c[1], best[2] = c[2];
    }
  }
  const double bn = std::sqrt(best_norm);
  const double e0[3] = {bn > 0 ? best[0] / bn : 1.0, bn > 0 ? best[1] / bn : 0.0, bn > 0 ? best[2] / bn : 0.0};
  // an orthonormal basis (u, w) of the plane orthogonal to e0, and m restricted to it
  double u[3];
  if (std::fabs(e0[0]) > std::fabs(e0[1])) {
    const double n = std::sqrt(e0[0] * e0[0] + e0[2] * e0[2]);
    u[0] = -e0[2] / n, u[1] = 0.0, u[2] = e0[0] / n;
  } else {
    const double n = std::sqrt(e0[1] * e0[1] + e0[2] * e0[2]);
    u[0] = 0.0, u[1] = e0[2] / n, u[2] = -e0[1] / n;
  }
  const double w[3] = {e0[1] * u[2] - e0[2] * u[1], e0[2] * u[0] - e0[0] * u[2], e0[0] * u[1] - e0[1] * u[0]};
  auto form = [&m](const double* x, const double* y) {  // x^T m y
    double sum = 0.0;
    for (int i = 0; i < 3; ++i) sum += x[i] * (m[3 * i] * y[0] + m[3 * i + 1] * y[1] + m[3 * i + 2] * y[2]);
    return sum;
  };
  const double s00 = form(u, u), s01 = form(u, w), s11 = form(w, w);
  double c = 1.0, s = 0.0, t = 0.0;
  if (s01 != 0.0) {
    const double theta = (s11 - s00) / (2.0 * s01);
    t = std::copysign(1.0, theta) / (std::fabs(theta) + std::sqrt(theta * theta + 1.0));
    c = 1.0 / std::sqrt(t * t + 1.0), s = t * c;
  }
  const double e1[3] = {c * u[0] - s * w[0], c * u[1] - s * w[1], c * u[2] - s * w[2]};
  const double e2[3] = {s * u[0] + c * w[0], s * u[1] + c * w[1], s * u[2] + c * w[2]};
  values[0] = form(e0, e0) * scale, values[1] = (s00 - t * s01) * scale, values[2] = (s11 + t * s01) * scale;
  for (int k = 0; k < 3; ++k) v[3 * k] = e0[k], v[3 * k + 1] = e1[k], v[3 * k + 2] = e2[k];
}

// Unit quaternion (w, x, y, z) of the rotation m (row-major, det +1): of the four equivalent
// Shepperd forms, the one with the largest pivot.
void matrix_to_quat(const double m[9], float q[4]) {
  const double tr = m[0] + m[4] + m[8];
  double w, x, y, z;
  if (tr >= m[0] && tr >= m[4] && tr >= m[8]) {
    const double s = 2.0 * std::sqrt(std::max(1.0 + tr, 1e-30));
    w = 0.25 * s, x = (m[7] - m[5]) / s, y = (m[2] - m[6]) / s, z = (m[3] - m[1]) / s;
  } else if (m[0] >= m[4] && m[0] >= m[8]) {
    const double s = 2.0 * std::sqrt(std::max(1.0 + m[0] - m[4] - m[8], 1e-30));
    w = (m[7] - m[5]) / s, x = 0.25 * s, y = (m[1] + m[3]) / s, z = (m[2] + m[6]) / s;
  } else if (m[4] >= m[8]) {
    const double s = 2.0 * std::sqrt(std::max(1.0 + m[4] - m[0] - m[8], 1e-30));
    w = (m[2] - m[6]) / s, x = (m[1] + m[3]) / s, y = 0.25 * s, z = (m[5] + m[7]) / s;
  } else {
    const double s = 2.0 * std::sqrt(std::max(1.0 + m[8] - m[0] - m[4], 1e-30));
    w = (m[3] - m[1]) / s, x = (m[2] + m[6]) / s, y = (m[5] + m[7]) / s, z = 0.25 * s;
  }
  const double n = std::sqrt(w * w + x * x + y * y + z * z);
  q[0] = static_cast<float>(w / n), q[1] = static_cast<float>(x / n), q[2] = static_cast<float>(y / n),
  q[3] = static_cast<float>(z / n);
}

// The covariance R S^2 R^T + sigma^2 u u^T is decomposed in the Gaussian's own axes, where it is
// S^2 + sigma^2 w w^T with w = R^T u (the same matrix, rotated: a diagonal plus a rank-one term),
// and the eigenvectors found there are rotated back by R.
void extend_one(const float* p, const float* q_in, const float* s_in, float sigma, float* q_out, float* s_out) {
  double w = q_in[0], x = q_in[1], y = q_in[2], z = q_in[3];
  const double qn = std::sqrt(w * w + x * x + y * y + z * z);
  w /= qn, x /= qn, y /= qn, z /= qn;
  const double r[9] = {1 - 2 * (y * y + z * z), 2 * (x * y - w * z),     2 * (x * z + w * y),
                       2 * (x * y + w * z),     1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
                       2 * (x * z - w * y),     2 * (y * z + w * x),     1 - 2 * (x * x + y * y)};
  const double var[3] = {std::exp(2.0 * s_in[0]), std::exp(2.0 * s_in[1]), std::exp(2.0 * s_in[2])};
  const double pn = std::sqrt(double(p[0]) * p[0] + double(p[1]) * p[1] + double(p[2]) * p[2]);
  const double u[3] = {p[0] / pn, p[1] / pn, p[2] / pn};
  double ray[3];  // R^T u
  for (int k = 0; k < 3; ++k) ray[k] = r[k] * u[0] + r[3 + k] * u[1] + r[6 + k] * u[2];
  const double extra = double(sigma) * sigma;
  double cov[9];
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) cov[3 * i + j] = (i == j ? var[i] : 0.0) + extra * ray[i] * ray[j];
  double values[3], local[9], v[9];
  eigen3(cov, values, local);
  for (int i = 0; i < 3; ++i)  // v = R local
    for (int j = 0; j < 3; ++j) v[3 * i + j] = r[3 * i] * local[j] + r[3 * i + 1] * local[3 + j] + r[3 * i + 2] * local[6 + j];
  const double det = v[0] * (v[4] * v[8] - v[5] * v[7]) - v[1] * (v[3] * v[8] - v[5] * v[6]) + v[2] * (v[3] * v[7] - v[4] * v[6]);
  if (det < 0)
    for (int k = 0; k < 3; ++k) v[3 * k + 2] = -v[3 * k + 2];
  matrix_to_quat(v, q_out);
  for (int k = 0; k < 3; ++k) s_out[k] = static_cast<float>(0.5 * std::log(std::max(values[k], 1e-30)));
}

std::tuple<at::Tensor, at::Tensor> extend_along_rays(const at::Tensor& points_in, const at::Tensor& quats_in,
                                                     const at::Tensor& log_scales_in, const at::Tensor& sigma_in) {
  TORCH_CHECK(points_in.dim() == 2 && points_in.size(1) == 3, "extend_along_rays: points must be [N, 3]");
  const int64_t n = points_in.size(0);
  TORCH_CHECK(quats_in.dim() == 2 && quats_in.size(0) == n && quats_in.size(1) == 4, "extend_along_rays: quats must be [N, 4]");
  TORCH_CHECK(log_scales_in.dim() == 2 && log_scales_in.size(0) == n && log_scales_in.size(1) == 3,
              "extend_along_rays: log_scales must be [N, 3]");
  TORCH_CHECK(sigma_in.dim() == 1 && sigma_in.size(0) == n, "extend_along_rays: sigma must be [N]");
  const at::Tensor points = points_in.to(at::kFloat).contiguous();
  const at::Tensor quats = quats_in.to(at::kFloat).contiguous();
  const at::Tensor log_scales = log_scales_in.to(at::kFloat).contiguous();
  const at::Tensor sigma = sigma_in.to(at::kFloat).contiguous();
  at::Tensor quats_out = quats.clone();
  at::Tensor scales_out = log_scales.clone();
  const float* p = points.data_ptr<float>();
  const float* q = quats.data_ptr<float>();
  const float* s = log_scales.data_ptr<float>();
  const float* sg = sigma.data_ptr<float>();
  float* qo = quats_out.data_ptr<float>();
  float* so = scales_out.data_ptr<float>();
  at::parallel_for(0, n, 4096, [&](int64_t begin, int64_t end) {
    for (int64_t i = begin; i < end; ++i) {
      if (!(sg[i] > 0.0f)) continue;  // unchanged (copied)
      extend_one(p + 3 * i, q + 4 * i, s + 3 * i, sg[i], qo + 4 * i, so + 3 * i);
    }
  });
  return {quats_out, scales_out};
}

// The footprint rule of per-pixel maps (drivingscene.gaussians.assembly.pixel_footprints): each
// pixel's Gaussian, at its unprojected mean, shrunk (shape kept) until its largest sigma in its
// own view is at most max_footprint pixels, then widened by the isotropic variance
// floor * (z / f)^2. float32; the shrunk variances are the variances times the shrink's ratio
// (the torch path takes their logarithm and exponential in between: the same up to rounding).
at::Tensor pixel_footprints(const at::Tensor& depth_in, const at::Tensor& intrinsics_in, const at::Tensor& quats_in,
                            const at::Tensor& log_scales_in, double max_footprint, double floor) {
  TORCH_CHECK(depth_in.dim() == 3, "pixel_footprints: depth must be [V, H, W]");
  const int64_t views = depth_in.size(0), height = depth_in.size(1), width = depth_in.size(2);
  TORCH_CHECK(intrinsics_in.dim() == 3 && intrinsics_in.size(0) == views && intrinsics_in.size(1) == 3 &&
                  intrinsics_in.size(2) == 3,
              "pixel_footprints: intrinsics must be [V, 3, 3]");
  TORCH_CHECK(quats_in.dim() == 4 && quats_in.size(0) == views && quats_in.size(1) == height &&
                  quats_in.size(2) == width && quats_in.size(3) == 4,
              "pixel_footprints: quats must be [V, H, W, 4]");
  TORCH_CHECK(log_scales_in.dim() == 4 && log_scales_in.size(0) == views && log_scales_in.size(1) == height &&
                  log_scales_in.size(2) == width && log_scales_in.size(3) == 3,
              "pixel_footprints: log_scales must be [V, H, W, 3]");
  const at::Tensor depth = depth_in.to(at::kFloat).contiguous();
  const at::Tensor intrinsics = intrinsics_in.to(at::kFloat).contiguous();
  const at::Tensor quats = quats_in.to(at::kFloat).contiguous();
  const at::Tensor log_scales = log_scales_in.to(at::kFloat).contiguous();
  at::Tensor out = at::empty_like(log_scales);
  const float* d = depth.data_ptr<float>();
  const float* k = intrinsics.data_ptr<float>();
  const float* q = quats.data_ptr<float>();
  const float* s = log_scales.data_ptr<float>();
  float* o = out.data_ptr<float>();
  const float cap2 = static_cast<float>(max_footprint * max_footprint);
  const float floor_f = static_cast<float>(floor);
  at::parallel_for(0, views * height, 8, [&](int64_t begin, int64_t end) {
    for (int64_t row = begin; row < end; ++row) {
      const int64_t view = row / height;
      const float* kv = k + 9 * view;
      const float fx = kv[0], skew = kv[1], cx = kv[2], fy = kv[4], cy = kv[5];
      const float yn = (static_cast<float>(row % height) - cy) / fy;
      for (int64_t col = 0; col < width; ++col) {
        const int64_t i = row * width + col;
        const float depth_c = std::max(d[i], 1e-3f);
        const float xn = (static_cast<float>(col) - cx - skew * yn) / fx;
        const float px = xn * depth_c, py = yn * depth_c, z = depth_c;
        const float* qi = q + 4 * i;
        const float* si = s + 3 * i;
        float* oi = o + 3 * i;
        float var[3], ratio = 1.0f;  // ratio: the variances' shrink factor (the cap)
        for (int c = 0; c < 3; ++c) var[c] = std::exp(2 * si[c]);
        if (cap2 > 0.0f) {
          const float norm = std::max(std::sqrt(qi[0] * qi[0] + qi[1] * qi[1] + qi[2] * qi[2] + qi[3] * qi[3]), 1e-12f);
          const float w = qi[0] / norm, qx = qi[1] / norm, qy = qi[2] / norm, qz = qi[3] / norm;
          const float rot[3][3] = {{1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy + w * qz), 2 * (qx * qz - w * qy)},
                                   {2 * (qx * qy - w * qz), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz + w * qx)},
                                   {2 * (qx * qz + w * qy), 2 * (qy * qz - w * qx), 1 - 2 * (qx * qx + qy * qy)}};
          const float u = px / z, v = py / z, gx = fx / z, gy = fy / z;
          float a = 0.0f, b = 0.0f, cc = 0.0f;
          for (int c = 0; c < 3; ++c) {  // column c of R, with its variance
            const float m0 = gx * (rot[c][0] - u * rot[c][2]), m1 = gy * (rot[c][1] - v * rot[c][2]);
            a += m0 * m0 * var[c], b += m0 * m1 * var[c], cc += m1 * m1 * var[c];
          }
          const float half = 0.5f * (a - cc);
          const float largest = 0.5f * (a + cc) + std::sqrt(half * half + b * b);
          ratio = std::min(cap2 / std::max(largest, 1e-20f), 1.0f);
        }
        if (floor_f > 0.0f) {  // exp(2 (s + shrink)) = var * ratio: no logarithm and exponential between
          const float step = 2 * z / (fx + fy);
          const float extra = floor_f * (step * step);
          for (int c = 0; c < 3; ++c) oi[c] = 0.5f * std::log(var[c] * ratio + extra);
        } else {
          const float shrink = 0.5f * std::log(ratio);
          for (int c = 0; c < 3; ++c) oi[c] = si[c] + shrink;
        }
      }
    }
  });
  return out;
}

}  // namespace

TORCH_LIBRARY_FRAGMENT(drivingscene_render, m) {
  m.def("extend_along_rays(Tensor points, Tensor quats, Tensor log_scales, Tensor sigma) -> (Tensor, Tensor)",
        &extend_along_rays);
  m.def("pixel_footprints(Tensor depth, Tensor intrinsics, Tensor quats, Tensor log_scales, float max_footprint, "
        "float floor) -> Tensor",
        &pixel_footprints);
}
