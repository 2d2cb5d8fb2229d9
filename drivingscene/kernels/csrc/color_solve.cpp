// The colour solve of drivingscene.render.color_solve over the images' own layers: each image's
// splats alone, in compositing order (image, then depth); each splat stands for a set of its
// image's pixels (its own pixel; a merged block's pixels, gaussians/parsimony.py).
//
// Per (camera, band of rows) task, the pair finder's scatter (find_pairs.cpp: the same cut, early
// stop and layer cap, the alphas from a float32 exp: the torch path's up to rounding) lists each
// pixel's splats into a buffer that stays in cache; the compositing weights of composite_forward (surface averaging with `tolerance`, black
// background; front_group.h) are formed from those alphas once, with each pixel's accumulated
// alpha A[p], and kept packed per task. Then `iterations` Jacobi (Van Cittert) steps: the residual
//     r(p) = target(p) - sum_k w_k c_k / max(A[p], 1e-6)
// at every pixel some splat stands for, where A[p] >= min_coverage, then for every splat i
//     c_i <- clamp(c_i + mean of r over i's pixels where it is defined, 0, max_color)
// (c_i kept where it is defined at none of them): each step one sparse product over memory that
// neighbours the pixel, no Gaussian evaluated again. A splat that stands for its own pixel alone
// is the per-pixel solve.
// The reference is the torch path of render.color_solve._solve_splats (a compositing pass per step).
#include <ATen/ATen.h>
#include <ATen/Parallel.h>
#include <torch/library.h>

#include "front_group.h"
#include "pairs.h"

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <limits>
#include <memory>
#include <vector>

namespace {

using drivingscene_front::front_weights;
using drivingscene_front::FrontWeights;
using drivingscene_front::joins_front;
using drivingscene_pairs::kBandRows;

// One task's pixels: their lists packed (source splat and weight per pair), list ends, coverage.
struct TaskLists {
  int64_t first = 0, count = 0;  // the task's pixels: first .. first + count (row-major, global)
  std::unique_ptr<int32_t[]> sources;
  std::unique_ptr<float[]> weights;
  std::unique_ptr<int32_t[]> ends;  // [count] end of each pixel's list in sources / weights
  std::unique_ptr<float[]> cover;   // [count]
};

// The band's lists (ids and alphas, max_layers per pixel) to packed weights (see the top comment).
void pack_weights(const int32_t* ids, const float* alphas, const int32_t* counts, int64_t max_layers, const float* depths,
                  float tol, TaskLists& out) {
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
      src[k] = id[k];
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

// One step's residual over a task's pixels (kChannels of them; 0: `channels`): r(p) where a splat
// stands for p and its coverage reaches `least`, NaN elsewhere.
template <int kChannels>
void residual(const TaskLists& l, const uint8_t* stood_for, const float* cur, const float* tgt, float* res, int64_t channels_in,
              float least) {
  const int64_t channels = kChannels > 0 ? kChannels : channels_in;
  float rgb[kChannels > 0 ? kChannels : 16];
  int32_t start = 0;
  for (int64_t q = 0; q < l.count; ++q) {
    const int64_t p = l.first + q;
    const int32_t stop = l.ends[q];
    float* r = res + p * channels;
    if (!stood_for[p] || !(l.cover[q] >= least)) {
      for (int64_t ch = 0; ch < channels; ++ch) r[ch] = std::numeric_limits<float>::quiet_NaN();
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
    for (int64_t ch = 0; ch < channels; ++ch) r[ch] = tgt[p * channels + ch] - rgb[ch] * inv;
  }
}

}  // namespace

at::Tensor own_layer_solve(const at::Tensor& means2d, const at::Tensor& conics, const at::Tensor& opacities,
                           const at::Tensor& sigma_max, const at::Tensor& boxes, const at::Tensor& camera_offsets,
                           int64_t width, int64_t height, int64_t max_layers, const at::Tensor& depths_in,
                           const at::Tensor& member_offsets_in, const at::Tensor& members_in, const at::Tensor& target_in,
                           const at::Tensor& start_in, int64_t iterations, double tolerance, double max_color,
                           double min_coverage) {
  const drivingscene_pairs::Prepared pre =
      drivingscene_pairs::prepare(means2d, conics, opacities, sigma_max, boxes, camera_offsets, width, height, max_layers);
  const int64_t rows = means2d.size(0), pixels = pre.num_cams * height * width, tasks = pre.num_cams * pre.bands;
  TORCH_CHECK(target_in.dim() == 2 && target_in.size(0) == pixels && start_in.dim() == 2 && start_in.size(0) == rows &&
                  start_in.size(1) == target_in.size(1) && depths_in.numel() == rows && member_offsets_in.numel() == rows + 1,
              "own_layer_solve: expected depths [M], member_offsets [M + 1] and start [M, C] for the M splats, target [B * H * W, C]");
  TORCH_CHECK(pixels < (int64_t{1} << 31), "own_layer_solve: more than 2^31 pixels");
  const int64_t channels = target_in.size(1);
  TORCH_CHECK(channels >= 1 && channels <= 16, "own_layer_solve: expected 1 to 16 channels, found ", channels);
  const at::Tensor depths_t = depths_in.to(at::kFloat).contiguous();
  const at::Tensor offsets_t = member_offsets_in.to(at::kLong).contiguous(), members_t = members_in.to(at::kLong).contiguous();
  const float* depths = depths_t.data_ptr<float>();
  const int64_t* offsets = offsets_t.data_ptr<int64_t>();
  const int64_t* members = members_t.data_ptr<int64_t>();
  TORCH_CHECK(offsets[0] == 0 && offsets[rows] == members_t.numel(),
              "own_layer_solve: member_offsets must run from 0 to the number of members, ", members_t.numel());
  std::vector<uint8_t> stood_for(pixels, 0);
  for (int64_t i = 0; i < rows; ++i) {
    TORCH_CHECK(offsets[i] <= offsets[i + 1], "own_layer_solve: member_offsets must not decrease (splat ", i, ")");
    for (int64_t m = offsets[i]; m < offsets[i + 1]; ++m) {
      const int64_t p = members[m];
      TORCH_CHECK(p >= 0 && p < pixels, "own_layer_solve: member pixel ", p, " of splat ", i, " is outside the ", pixels, " pixels");
      TORCH_CHECK(!stood_for[p], "own_layer_solve: two splats stand for pixel ", p);
      stood_for[p] = 1;
    }
  }
  const at::Tensor target_t = target_in.to(at::kFloat).contiguous();
  const float hi = static_cast<float>(max_color), least = static_cast<float>(min_coverage);
  at::Tensor current = start_in.to(at::kFloat).clamp(0.0, max_color).contiguous();

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
                                       band_alphas.data(), band_counts.data(), false);
      pack_weights(band_ids.data(), band_alphas.data(), band_counts.data(), max_layers, depths, tol, lists[t]);
    }
  }
  const float* tgt = target_t.data_ptr<float>();
  std::vector<float> res(pixels * channels);
  for (int64_t it = 0; it < iterations; ++it) {
    float* cur = current.data_ptr<float>();
    at::parallel_for(0, tasks, 1, [&](int64_t begin, int64_t end) {
      for (int64_t t = begin; t < end; ++t) {
        if (channels == 3) {
          residual<3>(lists[t], stood_for.data(), cur, tgt, res.data(), channels, least);
        } else {
          residual<0>(lists[t], stood_for.data(), cur, tgt, res.data(), channels, least);
        }
      }
    });
    at::parallel_for(0, rows, 4096, [&](int64_t begin, int64_t end) {
      float sum[16];
      for (int64_t i = begin; i < end; ++i) {
        int64_t n = 0;
        for (int64_t ch = 0; ch < channels; ++ch) sum[ch] = 0.0f;
        for (int64_t m = offsets[i]; m < offsets[i + 1]; ++m) {
          const float* r = res.data() + members[m] * channels;
          if (std::isnan(r[0])) continue;
          ++n;
          for (int64_t ch = 0; ch < channels; ++ch) sum[ch] += r[ch];
        }
        if (n == 0) continue;
        float* c = cur + i * channels;
        for (int64_t ch = 0; ch < channels; ++ch) c[ch] = std::min(std::max(c[ch] + sum[ch] / n, 0.0f), hi);
      }
    });
  }
  return current;
}

TORCH_LIBRARY_FRAGMENT(drivingscene_render, m) {
  m.def("own_layer_solve(Tensor means2d, Tensor conics, Tensor opacities, Tensor sigma_max, Tensor boxes, Tensor camera_offsets, "
        "int width, int height, int max_layers, Tensor depths, Tensor member_offsets, Tensor members, Tensor target, Tensor start, "
        "int iterations, "
        "float tolerance, float max_color, float min_coverage) -> Tensor",
        &own_layer_solve);
}
