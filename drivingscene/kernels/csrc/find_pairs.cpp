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

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

namespace {

constexpr int kBandRows = 8;
constexpr float kMaxAlpha = 0.99f;
constexpr float kMinTransmittance = 1e-4f;

struct Bins {
  std::vector<int64_t> offsets;  // [tasks + 1]
  std::vector<int32_t> ids;      // splat ids, depth order within each task
};

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

struct SplatArrays {
  const float* means2d;
  const float* conics;
  const float* opacities;
  const float* sigma_max;
  const int32_t* boxes;
};

// Scatter the band's splats, front to back, into its rows [row0, row1) of camera `cam`.
void scatter_band(const SplatArrays& s, const int32_t* ids, int64_t count, int64_t cam, int row0, int row1,
                  int width, int height, int max_layers, int32_t* out) {
  const int npix = (row1 - row0) * width;
  std::vector<float> trans(npix, 1.0f);
  std::vector<int32_t> layers(npix, 0);
  std::vector<uint8_t> done(npix, 0);
  int num_done = 0;
  int32_t* out_band = out + (cam * height + row0) * static_cast<int64_t>(width) * max_layers;
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
        const float alpha = std::min(kMaxAlpha, opacity * static_cast<float>(std::exp(-static_cast<double>(sigma))));
        const float next = trans[p] * (1.0f - alpha);
        if (next < kMinTransmittance) {
          done[p] = 1;
          ++num_done;
          continue;
        }
        out_band[static_cast<int64_t>(p) * max_layers + layers[p]] = j;
        trans[p] = next;
        if (++layers[p] == max_layers) {
          done[p] = 1;
          ++num_done;
        }
      }
    }
  }
}

void check_input(const at::Tensor& t, at::ScalarType dtype, int64_t cols, const char* name) {
  TORCH_CHECK(t.device().is_cpu(), name, " must be a CPU tensor");
  TORCH_CHECK(t.scalar_type() == dtype, name, " has dtype ", t.scalar_type(), ", expected ", dtype);
  TORCH_CHECK(t.is_contiguous(), name, " must be contiguous");
  if (cols > 0) TORCH_CHECK(t.dim() == 2 && t.size(1) == cols, name, " must be [M, ", cols, "], found ", t.sizes());
}

}  // namespace

// Returns [B * H * W, max_layers] int32 splat ids (row-major pixels per camera), -1 where empty.
at::Tensor find_pairs(const at::Tensor& means2d, const at::Tensor& conics, const at::Tensor& opacities,
                      const at::Tensor& sigma_max, const at::Tensor& boxes, const at::Tensor& camera_offsets,
                      int64_t width, int64_t height, int64_t max_layers) {
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
  at::Tensor out = at::full({num_cams * height * width, max_layers}, -1, means2d.options().dtype(at::kInt));
  const Bins bins = bin_by_band(boxes.data_ptr<int32_t>(), camera_offsets.data_ptr<int64_t>(), num_cams, bands, height);
  const SplatArrays s{means2d.data_ptr<float>(), conics.data_ptr<float>(), opacities.data_ptr<float>(),
                      sigma_max.data_ptr<float>(), boxes.data_ptr<int32_t>()};
  int32_t* out_ptr = out.data_ptr<int32_t>();
  const int64_t tasks = num_cams * bands;
#pragma omp parallel for schedule(dynamic, 1) num_threads(at::get_num_threads())
  for (int64_t t = 0; t < tasks; ++t) {
    const int64_t cam = t / bands, band = t % bands;
    const int row0 = static_cast<int>(band * kBandRows);
    const int row1 = static_cast<int>(std::min<int64_t>(height, row0 + kBandRows));
    scatter_band(s, bins.ids.data() + bins.offsets[t], bins.offsets[t + 1] - bins.offsets[t], cam, row0, row1,
                 static_cast<int>(width), static_cast<int>(height), static_cast<int>(max_layers), out_ptr);
  }
  return out;
}

TORCH_LIBRARY(drivingscene_render, m) {
  m.def(
      "find_pairs(Tensor means2d, Tensor conics, Tensor opacities, Tensor sigma_max, Tensor boxes, "
      "Tensor camera_offsets, int width, int height, int max_layers) -> Tensor",
      &find_pairs);
}
