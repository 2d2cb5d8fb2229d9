// The plane-sweep correlation of D's matching head (the optional compiled path of
// drivingscene.models.matching.correlate, forward and backward).
//
// plane_sweep_correlate: for every target image b, source slot s, plane p and pixel (y, x): the
// source feature vector of image sources[b, s] sampled bilinearly at uv[b, s, p, y, x] (taps
// outside the image count as 0, as grid_sample with align_corners=True and padding "zeros"), dot
// the target's feature vector at (y, x); 0 where valid[b, s, p, y, x] is false. The torch path
// warps every plane as a full feature map ([B S, C, P H, W] floats, ~300 MB at 6 cameras,
// 48 x 88, 32 planes, 16 channels) and multiplies; this kernel reads both feature maps
// channels-last once and keeps one row of results: the same sums in another order (float
// rounding; the tests compare them).
//
// plane_sweep_correlate_backward: the gradient of sum(grad_out * cost) with respect to the
// features, which appear twice: as the target (the sampled source vector times grad_out) and as
// the source (scattered to the four bilinear taps, weight times grad_out times the target
// vector). Targets are split between threads; the scattered source gradients go to one buffer per
// thread, summed at the end (no atomics).
#include <ATen/ATen.h>
#include <ATen/Parallel.h>
#include <torch/library.h>

#include <algorithm>
#include <cmath>
#include <vector>

namespace {

// Adds weight * source[y][x][:] (channels-last row of `channels`) dot `target` to `acc` if
// (x, y) is inside the image.
inline float tap(const float* source, const float* target, int64_t x, int64_t y, int64_t height, int64_t width,
                 int64_t channels, float weight) {
  if (x < 0 || y < 0 || x >= width || y >= height || weight == 0.0f) return 0.0f;
  const float* f = source + (y * width + x) * channels;
  float dot = 0.0f;
  for (int64_t c = 0; c < channels; ++c) dot += f[c] * target[c];
  return weight * dot;
}

// The bilinear taps of (x, y): top-left pixel and the four weights (top-left, top-right,
// bottom-left, bottom-right).
struct Taps {
  int64_t x0, y0;
  float w[4];
};

inline Taps taps_of(float x, float y) {
  const float fx = std::floor(x), fy = std::floor(y);
  const float wx = x - fx, wy = y - fy;
  return {static_cast<int64_t>(fx), static_cast<int64_t>(fy),
          {(1.0f - wx) * (1.0f - wy), wx * (1.0f - wy), (1.0f - wx) * wy, wx * wy}};
}

struct Checked {
  at::Tensor features, sources, uv, valid;  // features channels-last [B, H, W, C]
  int64_t batch, height, width, channels, slots, planes;
};

Checked check_inputs(const char* name, const at::Tensor& features_in, const at::Tensor& sources_in, const at::Tensor& uv_in,
                     const at::Tensor& valid_in) {
  TORCH_CHECK(features_in.dim() == 4, name, ": expected features [B, C, H, W]");
  TORCH_CHECK(uv_in.dim() == 6 && uv_in.size(5) == 2, name, ": expected uv [B, S, P, H, W, 2]");
  TORCH_CHECK(valid_in.dim() == 5, name, ": expected valid [B, S, P, H, W]");
  TORCH_CHECK(sources_in.dim() == 2, name, ": expected sources [B, S]");
  Checked c{features_in.to(at::kFloat).permute({0, 2, 3, 1}).contiguous(), sources_in.to(at::kLong).contiguous(),
            uv_in.to(at::kFloat).contiguous(), valid_in.to(at::kBool).contiguous(), 0, 0, 0, 0, 0, 0};
  c.batch = c.features.size(0);
  c.height = c.features.size(1);
  c.width = c.features.size(2);
  c.channels = c.features.size(3);
  c.slots = c.uv.size(1);
  c.planes = c.uv.size(2);
  TORCH_CHECK(c.uv.size(0) == c.batch && c.uv.size(3) == c.height && c.uv.size(4) == c.width, name, ": uv does not match features");
  TORCH_CHECK(c.valid.sizes() == c.uv.sizes().slice(0, 5), name, ": valid does not match uv");
  TORCH_CHECK(c.sources.size(0) == c.batch && c.sources.size(1) == c.slots, name, ": sources does not match uv");
  return c;
}

}  // namespace

at::Tensor plane_sweep_correlate(const at::Tensor& features_in, const at::Tensor& sources_in, const at::Tensor& uv_in,
                                 const at::Tensor& valid_in) {
  const Checked c = check_inputs("plane_sweep_correlate", features_in, sources_in, uv_in, valid_in);
  const int64_t height = c.height, width = c.width, channels = c.channels, slots = c.slots, planes = c.planes;
  at::Tensor out = at::zeros({c.batch, slots, planes, height, width}, c.features.options());
  const float* feat = c.features.data_ptr<float>();
  const int64_t* src = c.sources.data_ptr<int64_t>();
  const float* coords = c.uv.data_ptr<float>();
  const bool* ok = c.valid.data_ptr<bool>();
  float* o = out.data_ptr<float>();
  const int64_t pixels = height * width, image = pixels * channels;
  at::parallel_for(0, c.batch * slots * planes, 1, [&](int64_t begin, int64_t end) {
    for (int64_t job = begin; job < end; ++job) {
      const int64_t b = job / (slots * planes), s = (job / planes) % slots;
      const int64_t source = src[b * slots + s];
      if (source < 0) continue;
      const float* target = feat + b * image;
      const float* other = feat + source * image;
      const float* xy = coords + job * pixels * 2;
      const bool* mask = ok + job * pixels;
      float* dst = o + job * pixels;
      for (int64_t i = 0; i < pixels; ++i) {
        if (!mask[i]) continue;
        const Taps k = taps_of(xy[2 * i], xy[2 * i + 1]);
        const float* t = target + i * channels;
        dst[i] = tap(other, t, k.x0, k.y0, height, width, channels, k.w[0]) +
                 tap(other, t, k.x0 + 1, k.y0, height, width, channels, k.w[1]) +
                 tap(other, t, k.x0, k.y0 + 1, height, width, channels, k.w[2]) +
                 tap(other, t, k.x0 + 1, k.y0 + 1, height, width, channels, k.w[3]);
      }
    }
  });
  return out;
}

at::Tensor plane_sweep_correlate_backward(const at::Tensor& features_in, const at::Tensor& sources_in, const at::Tensor& uv_in,
                                          const at::Tensor& valid_in, const at::Tensor& grad_in) {
  const Checked c = check_inputs("plane_sweep_correlate_backward", features_in, sources_in, uv_in, valid_in);
  const at::Tensor grad = grad_in.to(at::kFloat).contiguous();
  TORCH_CHECK(grad.sizes() == c.valid.sizes(), "plane_sweep_correlate_backward: grad does not match valid");
  const int64_t height = c.height, width = c.width, channels = c.channels, slots = c.slots, planes = c.planes;
  const int64_t pixels = height * width, image = pixels * channels;
  const int threads = std::max(1, at::get_num_threads());
  // [threads + 1, B, H, W, C]: row 0 the target gradients (each target is one thread's), rows 1..
  // each thread's scattered source gradients.
  at::Tensor buffers = at::zeros({threads + 1, c.batch, height, width, channels}, c.features.options());
  const float* feat = c.features.data_ptr<float>();
  const int64_t* src = c.sources.data_ptr<int64_t>();
  const float* coords = c.uv.data_ptr<float>();
  const bool* ok = c.valid.data_ptr<bool>();
  const float* g = grad.data_ptr<float>();
  float* grad_target = buffers.data_ptr<float>();
  at::parallel_for(0, c.batch, 1, [&](int64_t begin, int64_t end) {
    float* grad_source = grad_target + (1 + at::get_thread_num()) * c.batch * image;
    std::vector<float> vec(channels);
    for (int64_t b = begin; b < end; ++b) {
      const float* target = feat + b * image;
      float* gt = grad_target + b * image;
      for (int64_t s = 0; s < slots; ++s) {
        const int64_t source = src[b * slots + s];
        if (source < 0) continue;
        const float* other = feat + source * image;
        float* gs = grad_source + source * image;
        for (int64_t p = 0; p < planes; ++p) {
          const int64_t job = (b * slots + s) * planes + p;
          const float* xy = coords + job * pixels * 2;
          const bool* mask = ok + job * pixels;
          const float* gj = g + job * pixels;
          for (int64_t i = 0; i < pixels; ++i) {
            if (!mask[i] || gj[i] == 0.0f) continue;
            const Taps k = taps_of(xy[2 * i], xy[2 * i + 1]);
            const float* t = target + i * channels;
            std::fill(vec.begin(), vec.end(), 0.0f);
            for (int q = 0; q < 4; ++q) {
              const int64_t x = k.x0 + (q & 1), y = k.y0 + (q >> 1);
              if (x < 0 || y < 0 || x >= width || y >= height || k.w[q] == 0.0f) continue;
              const float* f = other + (y * width + x) * channels;
              float* gf = gs + (y * width + x) * channels;
              const float scatter = k.w[q] * gj[i];
              for (int64_t ch = 0; ch < channels; ++ch) {
                vec[ch] += k.w[q] * f[ch];
                gf[ch] += scatter * t[ch];
              }
            }
            float* gti = gt + i * channels;
            for (int64_t ch = 0; ch < channels; ++ch) gti[ch] += gj[i] * vec[ch];
          }
        }
      }
    }
  });
  return buffers.sum(0).permute({0, 3, 1, 2}).contiguous();
}

TORCH_LIBRARY_FRAGMENT(drivingscene_render, m) {
  m.def("plane_sweep_correlate(Tensor features, Tensor sources, Tensor uv, Tensor valid) -> Tensor", &plane_sweep_correlate);
  m.def("plane_sweep_correlate_backward(Tensor features, Tensor sources, Tensor uv, Tensor valid, Tensor grad) -> Tensor",
        &plane_sweep_correlate_backward);
}
