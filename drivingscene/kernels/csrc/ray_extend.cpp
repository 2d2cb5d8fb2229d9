// Gaussians extended along their view rays (the optional compiled path of
// drivingscene.gaussians.assembly.extend_along_rays_torch).
//
// Each Gaussian's covariance R S^2 R^T, in its source camera's axes, gains the variance sigma^2
// along the unit ray from the camera centre to its mean, and the sum is decomposed again into a
// rotation and three scales: a cyclic Jacobi eigen-decomposition of the symmetric 3x3 in double
// precision, per Gaussian (torch's batched eigh costs ~1 s for 340k of them on two cores). The
// result is the same covariance as the torch path up to float rounding (the tests compare
// covariances: eigenvector order and signs are arbitrary). Not differentiable.
#include <ATen/ATen.h>
#include <ATen/Parallel.h>
#include <torch/library.h>

#include <algorithm>
#include <cmath>

namespace {

// Eigen-decomposition of the symmetric a (row-major 3x3, destroyed): eigenvalues in `values`,
// eigenvectors as the columns of v (row-major), by cyclic Jacobi rotations until the off-diagonal
// is negligible against the diagonal (a few sweeps for 3x3).
void jacobi3(double a[9], double values[3], double v[9]) {
  for (int i = 0; i < 9; ++i) v[i] = (i % 4 == 0) ? 1.0 : 0.0;
  for (int sweep = 0; sweep < 16; ++sweep) {
    const double off = a[1] * a[1] + a[2] * a[2] + a[5] * a[5];
    const double diag = a[0] * a[0] + a[4] * a[4] + a[8] * a[8];
    if (off <= 1e-30 * diag || off == 0.0) break;
    for (int p = 0; p < 2; ++p) {
      for (int q = p + 1; q < 3; ++q) {
        const double apq = a[3 * p + q];
        if (apq == 0.0) continue;
        const double app = a[3 * p + p], aqq = a[3 * q + q];
        const double theta = (aqq - app) / (2.0 * apq);
        const double t = std::copysign(1.0, theta) / (std::fabs(theta) + std::sqrt(theta * theta + 1.0));
        const double c = 1.0 / std::sqrt(t * t + 1.0), s = t * c;
        for (int k = 0; k < 3; ++k) {  // a <- a J (columns p, q)
          const double akp = a[3 * k + p], akq = a[3 * k + q];
          a[3 * k + p] = c * akp - s * akq;
          a[3 * k + q] = s * akp + c * akq;
        }
        for (int k = 0; k < 3; ++k) {  // a <- J^T a (rows p, q)
          const double apk = a[3 * p + k], aqk = a[3 * q + k];
          a[3 * p + k] = c * apk - s * aqk;
          a[3 * q + k] = s * apk + c * aqk;
        }
        for (int k = 0; k < 3; ++k) {  // v <- v J
          const double vkp = v[3 * k + p], vkq = v[3 * k + q];
          v[3 * k + p] = c * vkp - s * vkq;
          v[3 * k + q] = s * vkp + c * vkq;
        }
      }
    }
  }
  values[0] = a[0], values[1] = a[4], values[2] = a[8];
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
  const double extra = double(sigma) * sigma;
  double cov[9];
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j)
      cov[3 * i + j] = r[3 * i] * r[3 * j] * var[0] + r[3 * i + 1] * r[3 * j + 1] * var[1] +
                       r[3 * i + 2] * r[3 * j + 2] * var[2] + extra * u[i] * u[j];
  double values[3], v[9];
  jacobi3(cov, values, v);
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

}  // namespace

TORCH_LIBRARY_FRAGMENT(drivingscene_render, m) {
  m.def("extend_along_rays(Tensor points, Tensor quats, Tensor log_scales, Tensor sigma) -> (Tensor, Tensor)",
        &extend_along_rays);
}
