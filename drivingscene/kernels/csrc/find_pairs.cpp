// Gaussian-pixel pair finding for drivingscene.render (the optional compiled path of composite.py).
//
// For every pixel, the first `max_layers` Gaussians (in the given front-to-back order) whose
// contribution passes the cut `sigma <= sigma_max`, with front-to-back transmittance and early stop:
// a Gaussian that would bring the transmittance below 1e-4 is dropped and the pixel stops (3DGS).
// The arithmetic mirrors `find_pairs_torch` in composite.py operation by operation (float32, no FMA
// contraction, alpha from a float64 exp rounded to float32) so both paths choose the same pairs.
//
// Work is split into (camera, band of rows) tasks run in parallel with OpenMP; inside a task,
// Gaussians are scattered into their pixel boxes in depth order, which touches each candidate
// pixel once (no per-tile scan of non-overlapping Gaussians).
#include <ATen/ATen.h>
#include <ATen/Parallel.h>
#include <torch/library.h>

#include "pairs.h"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

namespace {

using drivingscene_pairs::Bins;
using drivingscene_pairs::kBandRows;

constexpr float kMaxAlpha = 0.99f;
constexpr float kMinTransmittance = 1e-4f;

int64_t band_of(int32_t row, int64_t bands) {
  return std::min<int64_t>(std::max<int32_t>(row, 0) / kBandRows, bands - 1);
}

// Band lists: for each (camera, band), the splats whose pixel box meets the band, in splat order.
Bins bin_by_band(const int32_t* boxes, const int64_t* cam_offsets, int64_t num_cams, int64_t bands, int64_t height) {
  Bins bins;
  bins.offsets.assign(num_cams * bands + 1, 0);
  for (int64_t cam = 0; cam < num_cams; ++cam) {
    for (int64_t j = cam_offsets[cam]; j < cam_offsets[cam + 1]; ++j) {
      const int32_t* box = boxes + 4 * j;  // x0, x1, y0, y1 (inclusive, clipped)
      if (box[0] > box[1] || box[2] > box[3] || box[3] < 0 || box[2] >= height) continue;
      for (int64_t band = band_of(box[2], bands); band <= band_of(box[3], bands); ++band) {
        ++bins.offsets[cam * bands + band + 1];
      }
    }
  }
  for (size_t t = 1; t < bins.offsets.size(); ++t) bins.offsets[t] += bins.offsets[t - 1];
  bins.ids.resize(bins.offsets.back());
  std::vector<int64_t> cursor(bins.offsets.begin(), bins.offsets.end() - 1);
  for (int64_t cam = 0; cam < num_cams; ++cam) {
    for (int64_t j = cam_offsets[cam]; j < cam_offsets[cam + 1]; ++j) {
      const int32_t* box = boxes + 4 * j;
      if (box[0] > box[1] || box[2] > box[3] || box[3] < 0 || box[2] >= height) continue;
      for (int64_t band = band_of(box[2], bands); band <= band_of(box[3], bands); ++band) {
        bins.ids[cursor[cam * bands + band]++] = static_cast<int32_t>(j);
      }
    }
  }
  return bins;
}

void check_input(const at::Tensor& t, at::ScalarType dtype, int64_t cols, const char* name) {
  TORCH_CHECK(t.device().is_cpu(), name, " must be a CPU tensor");
  TORCH_CHECK(t.scalar_type() == dtype, name, " has dtype ", t.scalar_type(), ", expected ", dtype);
  TORCH_CHECK(t.is_contiguous(), name, " must be contiguous");
  if (cols > 0) TORCH_CHECK(t.dim() == 2 && t.size(1) == cols, name, " must be [M, ", cols, "], found ", t.sizes());
}

}  // namespace

namespace drivingscene_pairs {

Prepared prepare(const at::Tensor& means2d, const at::Tensor& conics, const at::Tensor& opacities, const at::Tensor& sigma_max,
                 const at::Tensor& boxes, const at::Tensor& camera_offsets, int64_t width, int64_t height, int64_t max_layers) {
  check_input(means2d, at::kFloat, 2, "means2d");
  check_input(conics, at::kFloat, 3, "conics");
  check_input(opacities, at::kFloat, 0, "opacities");
  check_input(sigma_max, at::kFloat, 0, "sigma_max");
  check_input(boxes, at::kInt, 4, "boxes");
  check_input(camera_offsets, at::kLong, 0, "camera_offsets");
  TORCH_CHECK(max_layers > 0 && width > 0 && height > 0, "width, height and max_layers must be positive");
  const int64_t num_splats = means2d.size(0);
  TORCH_CHECK(conics.size(0) == num_splats && opacities.numel() == num_splats && sigma_max.numel() == num_splats &&
                  boxes.size(0) == num_splats,
              "means2d, conics, opacities, sigma_max and boxes must have the same length");
  const int64_t num_cams = camera_offsets.numel() - 1;
  TORCH_CHECK(num_cams >= 1, "camera_offsets must have B + 1 >= 2 entries");
  const int64_t* offsets = camera_offsets.data_ptr<int64_t>();
  TORCH_CHECK(offsets[0] == 0 && offsets[num_cams] == num_splats, "camera_offsets must run from 0 to M");
  for (int64_t b = 0; b < num_cams; ++b) TORCH_CHECK(offsets[b] <= offsets[b + 1], "camera_offsets must not decrease");
  const int64_t bands = (height + kBandRows - 1) / kBandRows;
  return Prepared{num_cams, bands, bin_by_band(boxes.data_ptr<int32_t>(), offsets, num_cams, bands, height),
                  SplatArrays{means2d.data_ptr<float>(), conics.data_ptr<float>(), opacities.data_ptr<float>(),
                              sigma_max.data_ptr<float>(), boxes.data_ptr<int32_t>()}};
}

void scatter_band(const SplatArrays& s, const int32_t* ids, int64_t count, int row0, int row1, int width, int max_layers,
                  int32_t* out_band, float* alpha_band, int32_t* counts, bool exact_exp) {
  const int npix = (row1 - row0) * width;
  std::vector<float> trans(npix, 1.0f);
  std::vector<int32_t> layers(npix, 0);
  std::vector<uint8_t> done(npix, 0);
  int num_done = 0;
  for (int64_t k = 0; k < count && num_done < npix; ++k) {
    const int32_t j = ids[k];
    const float gx = s.means2d[2 * j], gy = s.means2d[2 * j + 1];
    const float a = s.conics[3 * j], b = s.conics[3 * j + 1], c = s.conics[3 * j + 2];
    const float opacity = s.opacities[j], sigma_max = s.sigma_max[j];
    const int32_t* box = s.boxes + 4 * j;  // clipped again here: out-of-range boxes must not write outside
    const int x_lo = std::max<int>(box[0], 0), x_hi = std::min<int>(box[1], width - 1);
    const int y_lo = std::max<int>(box[2], row0), y_hi = std::min<int>(box[3], row1 - 1);
    for (int y = y_lo; y <= y_hi; ++y) {
      const float dy = static_cast<float>(y) - gy;
      const int row = (y - row0) * width;
      for (int x = x_lo; x <= x_hi; ++x) {
        const int p = row + x;
        if (done[p]) continue;
        const float dx = static_cast<float>(x) - gx;
        const float sigma = 0.5f * (a * dx * dx + c * dy * dy) + b * dx * dy;
        if (!(sigma <= sigma_max)) continue;
        const float falloff = exact_exp ? static_cast<float>(std::exp(-static_cast<double>(sigma))) : std::exp(-sigma);
        const float alpha = std::min(kMaxAlpha, opacity * falloff);
        const float next = trans[p] * (1.0f - alpha);
        if (next < kMinTransmittance) {
          done[p] = 1;
          ++num_done;
          continue;
        }
        out_band[static_cast<int64_t>(p) * max_layers + layers[p]] = j;
        if (alpha_band != nullptr) alpha_band[static_cast<int64_t>(p) * max_layers + layers[p]] = alpha;
        trans[p] = next;
        if (++layers[p] == max_layers) {
          done[p] = 1;
          ++num_done;
        }
      }
    }
  }
  if (counts != nullptr) std::copy(layers.begin(), layers.end(), counts);
}

}  // namespace drivingscene_pairs

using drivingscene_pairs::prepare;
using drivingscene_pairs::Prepared;
using drivingscene_pairs::scatter_band;

// Returns [B * H * W, max_layers] int32 splat ids (row-major pixels per camera), -1 where empty.
at::Tensor find_pairs(const at::Tensor& means2d, const at::Tensor& conics, const at::Tensor& opacities,
                      const at::Tensor& sigma_max, const at::Tensor& boxes, const at::Tensor& camera_offsets,
                      int64_t width, int64_t height, int64_t max_layers) {
  const Prepared pre = prepare(means2d, conics, opacities, sigma_max, boxes, camera_offsets, width, height, max_layers);
  at::Tensor out = at::full({pre.num_cams * height * width, max_layers}, -1, means2d.options().dtype(at::kInt));
  int32_t* out_ptr = out.data_ptr<int32_t>();
  const int64_t tasks = pre.num_cams * pre.bands;
#pragma omp parallel for schedule(dynamic, 1) num_threads(at::get_num_threads())
  for (int64_t t = 0; t < tasks; ++t) {
    const int64_t cam = t / pre.bands, band = t % pre.bands;
    const int row0 = static_cast<int>(band * kBandRows);
    const int row1 = static_cast<int>(std::min<int64_t>(height, row0 + kBandRows));
    int32_t* out_band = out_ptr + (cam * height + row0) * width * max_layers;
    scatter_band(pre.s, pre.bins.ids.data() + pre.bins.offsets[t], pre.bins.offsets[t + 1] - pre.bins.offsets[t], row0, row1,
                 static_cast<int>(width), static_cast<int>(max_layers), out_band, nullptr, nullptr);
  }
  return out;
}

// The pixel boxes of pair_inputs (render/composite.py): per splat, the box of the ellipse
// {d^T Q d <= 2 sigma_max} grown by a small margin, clipped to the image, [x0, x1, y0, y1] int32
// (empty, x0 > x1 or y0 > y1, where the conic, the cut or the radius says nothing is drawn). The
// same float64 operations in the same order as the torch path: the same boxes. Coordinates beyond
// int32 are kept empty (clamped to -1 and the image's size + 1) instead of overflowing.
at::Tensor splat_boxes(const at::Tensor& means2d, const at::Tensor& conics, const at::Tensor& sigma_max, const at::Tensor& radii,
                       int64_t width, int64_t height) {
  check_input(means2d, at::kFloat, 2, "means2d");
  check_input(conics, at::kFloat, 3, "conics");
  check_input(sigma_max, at::kFloat, 0, "sigma_max");
  check_input(radii, at::kFloat, 0, "radii");
  const int64_t num = means2d.size(0);
  TORCH_CHECK(conics.size(0) == num && sigma_max.numel() == num && radii.numel() == num,
              "means2d, conics, sigma_max and radii must have the same length");
  at::Tensor boxes = at::empty({num, 4}, means2d.options().dtype(at::kInt));
  const float* m = means2d.data_ptr<float>();
  const float* q = conics.data_ptr<float>();
  const float* sm = sigma_max.data_ptr<float>();
  const float* r = radii.data_ptr<float>();
  int32_t* out = boxes.data_ptr<int32_t>();
  const double size[2] = {static_cast<double>(width - 1), static_cast<double>(height - 1)};
  at::parallel_for(0, num, 4096, [&](int64_t begin, int64_t end) {
    for (int64_t j = begin; j < end; ++j) {
      const double a = q[3 * j], b = q[3 * j + 1], c = q[3 * j + 2];
      double det = a * c - b * b;
      bool ok = det > 0.0 && sm[j] > 0.0f && r[j] > 0.0f;
      if (!ok) det = 1.0;
      const double two_s = 2.0 * std::max(static_cast<double>(sm[j]), 0.0);
      const double half[2] = {std::sqrt(two_s * c / det) * (1.0 + 1e-3) + 1e-3, std::sqrt(two_s * a / det) * (1.0 + 1e-3) + 1e-3};
      const double centre[2] = {m[2 * j], m[2 * j + 1]};
      ok = ok && std::isfinite(centre[0]) && std::isfinite(centre[1]) && std::isfinite(half[0]) && std::isfinite(half[1]);
      for (int axis = 0; axis < 2; ++axis) {
        const double lo = ok ? std::max(std::ceil(centre[axis] - half[axis]), 0.0) : 0.0;
        const double hi = ok ? std::min(std::floor(centre[axis] + half[axis]), size[axis]) : -1.0;
        out[4 * j + 2 * axis] = static_cast<int32_t>(std::min(lo, size[axis] + 1.0));
        out[4 * j + 2 * axis + 1] = static_cast<int32_t>(std::max(hi, -1.0));
      }
    }
  });
  return boxes;
}

TORCH_LIBRARY(drivingscene_render, m) {
  m.def(
      "find_pairs(Tensor means2d, Tensor conics, Tensor opacities, Tensor sigma_max, Tensor boxes, "
      "Tensor camera_offsets, int width, int height, int max_layers) -> Tensor",
      &find_pairs);
  m.def("splat_boxes(Tensor means2d, Tensor conics, Tensor sigma_max, Tensor radii, int width, int height) -> Tensor", &splat_boxes);
}
