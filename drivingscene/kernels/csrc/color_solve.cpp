// The colour solve of drivingscene.render.color_solve over the images' own layers: each image's
// splats alone, each drawn at its own pixel, in compositing order (image, then depth).
//
// Per (camera, band of rows) task, the pair finder's scatter (find_pairs.cpp: the same cut, early
// stop and layer cap, the same alphas) lists each pixel's splats into a buffer that stays in
// cache; the compositing weights of composite_forward (surface averaging with `tolerance`, black
// background; front_group.h) are formed from those alphas once, with each pixel's accumulated
// alpha A[p], and kept packed per task beside the listed splats' pixels. Then `iterations` Jacobi
// (Van Cittert) steps, for every splat i at its pixel p_i,
//     c_i <- clamp(c_i + target(p_i) - sum_k w_k c_k / max(A[p_i], 1e-6), 0, max_color)
// over p_i's list where A[p_i] >= min_coverage (else c_i is kept): each step one sparse product
// over memory that neighbours the pixel (colours, targets and the result are per pixel: a pixel
// without a splat keeps its start), no Gaussian evaluated again.
// The reference is the torch path of solve_pixel_colors (a compositing pass per step).
#include <ATen/ATen.h>
#include <ATen/Parallel.h>
#include <torch/library.h>

#include "front_group.h"
#include "pairs.h"

#include <algorithm>
#include <atomic>
#include <cstdint>
#include <memory>
#include <vector>

namespace {

using drivingscene_front::front_weights;
using drivingscene_front::FrontWeights;
using drivingscene_front::joins_front;
using drivingscene_pairs::kBandRows;

// One task's pixels: their lists packed (source pixel and weight per pair), list ends, coverage.
struct TaskLists {
  int64_t first = 0, count = 0;  // the task's pixels: first .. first + count (row-major, global)
  std::unique_ptr<int32_t[]> sources;
  std::unique_ptr<float[]> weights;
  std::unique_ptr<int32_t[]> ends;  // [count] end of each pixel's list in sources / weights
  std::unique_ptr<float[]> cover;   // [count]
};

// The band's lists (ids and alphas, max_layers per pixel) to packed weights (see the top comment).
void pack_weights(const int32_t* ids, const float* alphas, const int32_t* counts, int64_t max_layers, const float* depths,
                  const int64_t* pixel, float tol, TaskLists& out) {
  int64_t total = 0;
  for (int64_t p = 0; p < out.count; ++p) total += counts[p];
  out.sources.reset(new int32_t[total]);
  out.weights.reset(new float[total]);
  out.ends.reset(new int32_t[out.count]);
  out.cover.reset(new float[out.count]);
  int64_t at = 0;
  for (int64_t p = 0; p < out.count; ++p) {
    const int32_t* id = ids + p * max_layers;
    const float* a = alphas + p * max_layers;
    int32_t* src = out.sources.get() + at;
    float* w = out.weights.get() + at;
    float trans = 1.0f, ws = 0.0f, f_sum = 0.0f, f_trans = 1.0f, z_limit = 0.0f;
    int64_t f_count = 0, f_end = 0;
    bool in_front = true;
    for (int64_t k = 0; k < counts[p]; ++k) {
      const float z = depths[id[k]];
      src[k] = static_cast<int32_t>(pixel[id[k]]);
      if (in_front && joins_front(f_count, tol, z, z_limit)) {
        if (f_count == 0) z_limit = z * (1.0f + tol);
        ++f_count;
        f_sum += a[k];
        f_trans *= 1.0f - a[k];
        f_end = k + 1;
        continue;
      }
      if (in_front) {
        in_front = false;
        trans = f_trans;
      }
      w[k] = a[k] * trans;
      trans = trans * (1.0f - a[k]);
      ws += w[k];
    }
    const FrontWeights fw = front_weights(f_count, f_sum, f_trans);
    for (int64_t k = 0; k < f_end; ++k) w[k] = a[k] * fw.scale;
    out.cover[p] = fw.cover + ws;
    at += counts[p];
    out.ends[p] = static_cast<int32_t>(at);
  }
}

// One Jacobi step over a task's pixels (colours per pixel, kChannels of them; 0: `channels`).
template <int kChannels>
void step(const TaskLists& l, const uint8_t* owned, const float* cur, const float* tgt, float* nxt, int64_t channels_in,
          float least, float hi) {
  const int64_t channels = kChannels > 0 ? kChannels : channels_in;
  float rgb[kChannels > 0 ? kChannels : 16];
  int32_t start = 0;
  for (int64_t q = 0; q < l.count; ++q) {
    const int64_t p = l.first + q;
    const int32_t stop = l.ends[q];
    const float* c = cur + p * channels;
    float* n = nxt + p * channels;
    if (!owned[p] || !(l.cover[q] >= least)) {
      for (int64_t ch = 0; ch < channels; ++ch) n[ch] = c[ch];
      start = stop;
      continue;
    }
    for (int64_t ch = 0; ch < channels; ++ch) rgb[ch] = 0.0f;
    for (int32_t k = start; k < stop; ++k) {
      const float w = l.weights[k];
      const float* s = cur + static_cast<int64_t>(l.sources[k]) * channels;
      for (int64_t ch = 0; ch < channels; ++ch) rgb[ch] += w * s[ch];
    }
    start = stop;
    const float inv = 1.0f / std::max(l.cover[q], 1e-6f);
    for (int64_t ch = 0; ch < channels; ++ch) {
      const float value = c[ch] + tgt[p * channels + ch] - rgb[ch] * inv;
      n[ch] = std::min(std::max(value, 0.0f), hi);
    }
  }
}

}  // namespace

at::Tensor own_layer_solve(const at::Tensor& means2d, const at::Tensor& conics, const at::Tensor& opacities,
                           const at::Tensor& sigma_max, const at::Tensor& boxes, const at::Tensor& camera_offsets,
                           int64_t width, int64_t height, int64_t max_layers, const at::Tensor& depths_in,
                           const at::Tensor& pixel_in, const at::Tensor& target_in, const at::Tensor& start_in,
                           int64_t iterations, double tolerance, double max_color, double min_coverage) {
  const drivingscene_pairs::Prepared pre =
      drivingscene_pairs::prepare(means2d, conics, opacities, sigma_max, boxes, camera_offsets, width, height, max_layers);
  const int64_t rows = means2d.size(0), pixels = pre.num_cams * height * width, tasks = pre.num_cams * pre.bands;
  TORCH_CHECK(target_in.dim() == 2 && target_in.size(0) == pixels && start_in.sizes() == target_in.sizes() &&
                  depths_in.numel() == rows && pixel_in.numel() == rows,
              "own_layer_solve: expected depths and pixel [M] for the M splats, target and start [B * H * W, C]");
  TORCH_CHECK(pixels < (int64_t{1} << 31), "own_layer_solve: more than 2^31 pixels");
  const int64_t channels = target_in.size(1);
  TORCH_CHECK(channels >= 1 && channels <= 16, "own_layer_solve: expected 1 to 16 channels, found ", channels);
  const at::Tensor depths_t = depths_in.to(at::kFloat).contiguous(), pixel_t = pixel_in.to(at::kLong).contiguous();
  const float* depths = depths_t.data_ptr<float>();
  const int64_t* pixel = pixel_t.data_ptr<int64_t>();
  std::vector<uint8_t> owned(pixels, 0);
  for (int64_t i = 0; i < rows; ++i) {
    TORCH_CHECK(pixel[i] >= 0 && pixel[i] < pixels, "own_layer_solve: pixel[", i, "] = ", pixel[i], " is outside the ", pixels,
                " pixels");
    TORCH_CHECK(!owned[pixel[i]], "own_layer_solve: two splats at pixel ", pixel[i]);
    owned[pixel[i]] = 1;
  }
  const at::Tensor target_t = target_in.to(at::kFloat).contiguous();
  at::Tensor current = start_in.to(at::kFloat).clone(at::MemoryFormat::Contiguous);
  {  // a pixel's own splat starts in range
    float* c = current.data_ptr<float>();
    const float hi = static_cast<float>(max_color);
    at::parallel_for(0, pixels, 4096, [&](int64_t begin, int64_t end) {
      for (int64_t p = begin; p < end; ++p) {
        if (!owned[p]) continue;
        for (int64_t ch = 0; ch < channels; ++ch) c[p * channels + ch] = std::min(std::max(c[p * channels + ch], 0.0f), hi);
      }
    });
  }
  at::Tensor next = at::empty_like(current);

  std::vector<TaskLists> lists(tasks);
  const float tol = static_cast<float>(tolerance);
#pragma omp parallel num_threads(at::get_num_threads())
  {
    std::vector<int32_t> band_ids(kBandRows * width * max_layers), band_counts(kBandRows * width);
    std::vector<float> band_alphas(kBandRows * width * max_layers);
#pragma omp for schedule(dynamic, 1)
    for (int64_t t = 0; t < tasks; ++t) {
      const int64_t cam = t / pre.bands, band = t % pre.bands;
      const int row0 = static_cast<int>(band * kBandRows);
      const int row1 = static_cast<int>(std::min<int64_t>(height, row0 + kBandRows));
      lists[t].first = (cam * height + row0) * width;
      lists[t].count = (row1 - row0) * width;
      drivingscene_pairs::scatter_band(pre.s, pre.bins.ids.data() + pre.bins.offsets[t], pre.bins.offsets[t + 1] - pre.bins.offsets[t],
                                       row0, row1, static_cast<int>(width), static_cast<int>(max_layers), band_ids.data(),
                                       band_alphas.data(), band_counts.data());
      pack_weights(band_ids.data(), band_alphas.data(), band_counts.data(), max_layers, depths, pixel, tol, lists[t]);
    }
  }
  const float hi = static_cast<float>(max_color), least = static_cast<float>(min_coverage);
  const float* tgt = target_t.data_ptr<float>();
  for (int64_t it = 0; it < iterations; ++it) {
    const float* cur = current.data_ptr<float>();
    float* nxt = next.data_ptr<float>();
    at::parallel_for(0, tasks, 1, [&](int64_t begin, int64_t end) {
      for (int64_t t = begin; t < end; ++t) {
        if (channels == 3) {
          step<3>(lists[t], owned.data(), cur, tgt, nxt, channels, least, hi);
        } else {
          step<0>(lists[t], owned.data(), cur, tgt, nxt, channels, least, hi);
        }
      }
    });
    std::swap(current, next);
  }
  return current;
}

TORCH_LIBRARY_FRAGMENT(drivingscene_render, m) {
  m.def("own_layer_solve(Tensor means2d, Tensor conics, Tensor opacities, Tensor sigma_max, Tensor boxes, Tensor camera_offsets, "
        "int width, int height, int max_layers, Tensor depths, Tensor pixel, Tensor target, Tensor start, int iterations, "
        "float tolerance, float max_color, float min_coverage) -> Tensor",
        &own_layer_solve);
}
