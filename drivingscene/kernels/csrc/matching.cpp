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

// The source feature vector (channels-last rows of `channels`) interpolated bilinearly at the
// taps `k` into `vec`, then dotted with `target`: the order of grid_sample and the torch path,
// the dot a vectorised reduction (`omp simd`: the same sum in another order). A tap outside the
// image counts as 0 (grid_sample's "zeros" padding): its weight is 0 and its index is clamped
// onto the image.
inline float interpolated_dot(const float* source, const float* target, const Taps& k, int64_t height, int64_t width,
                              int64_t channels, float* vec) {
  const bool left = k.x0 >= 0 && k.x0 < width, right = k.x0 + 1 >= 0 && k.x0 + 1 < width;
  const bool top = k.y0 >= 0 && k.y0 < height, bottom = k.y0 + 1 >= 0 && k.y0 + 1 < height;
  const int64_t x0 = std::min(std::max<int64_t>(k.x0, 0), width - 1), x1 = std::min(std::max<int64_t>(k.x0 + 1, 0), width - 1);
  const int64_t y0 = std::min(std::max<int64_t>(k.y0, 0), height - 1), y1 = std::min(std::max<int64_t>(k.y0 + 1, 0), height - 1);
  const float* f00 = source + (y0 * width + x0) * channels;
  const float* f01 = source + (y0 * width + x1) * channels;
  const float* f10 = source + (y1 * width + x0) * channels;
  const float* f11 = source + (y1 * width + x1) * channels;
  const float w0 = left && top ? k.w[0] : 0.0f, w1 = right && top ? k.w[1] : 0.0f;
  const float w2 = left && bottom ? k.w[2] : 0.0f, w3 = right && bottom ? k.w[3] : 0.0f;
#pragma omp simd
  for (int64_t c = 0; c < channels; ++c) vec[c] = w0 * f00[c] + w1 * f01[c] + w2 * f10[c] + w3 * f11[c];
  float dot = 0.0f;
#pragma omp simd reduction(+ : dot)
  for (int64_t c = 0; c < channels; ++c) dot += vec[c] * target[c];
  return dot;
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
    std::vector<float> sampled(channels);
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
        dst[i] = interpolated_dot(other, target + i * channels, taps_of(xy[2 * i], xy[2 * i + 1]), height, width, channels,
                                  sampled.data());
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

// plane_sweep_volume: the whole sweep of `MatchingHead` at inference in one pass per target row:
// for each target pixel and slot, the ray's image a r under the slot's homography part a (K_s R),
// then per plane d: hom = d (a r) + b, z = hom_z, uv = hom_xy / max(z, 1e-6); valid where
// z > min_z, uv inside [0, W - 1] x [0, H - 1], and (with masks) the source pixel nearest to uv
// (rounded half to even, as torch.round) sees the world; the costs; the validity; the share of
// valid planes; the parallax, the summed |uv_{p+1} - uv_p| over consecutive valid planes
// (models/matching.py: sweep_coordinates, sample_validity, sweep_parallax, correlate).
//
// A cost is `interpolated_dot`, as in plane_sweep_correlate. Every output value is written in the
// loop (0 where not valid): nothing is zero-filled first.
std::vector<at::Tensor> plane_sweep_volume(const at::Tensor& features_in, const at::Tensor& rays_in, const at::Tensor& a_in,
                                           const at::Tensor& b_in, const at::Tensor& sources_in, const at::Tensor& depths_in,
                                           const at::Tensor& source_valid_in, double min_z) {
  TORCH_CHECK(features_in.dim() == 4, "plane_sweep_volume: expected features [B, C, H, W]");
  const at::Tensor features = features_in.to(at::kFloat).permute({0, 2, 3, 1}).contiguous();
  const at::Tensor rays = rays_in.to(at::kFloat).contiguous();
  const at::Tensor a = a_in.to(at::kFloat).contiguous();
  const at::Tensor b = b_in.to(at::kFloat).contiguous();
  const at::Tensor sources = sources_in.to(at::kLong).contiguous();
  const at::Tensor depths = depths_in.to(at::kFloat).contiguous();
  const int64_t batch = features.size(0), height = features.size(1), width = features.size(2), channels = features.size(3);
  const int64_t slots = sources.size(1), planes = depths.size(0);
  TORCH_CHECK(rays.sizes() == at::IntArrayRef({batch, height, width, 3}), "plane_sweep_volume: expected rays [B, H, W, 3]");
  TORCH_CHECK(a.sizes() == at::IntArrayRef({batch, slots, 3, 3}) && b.sizes() == at::IntArrayRef({batch, slots, 3}),
              "plane_sweep_volume: expected a [B, S, 3, 3] and b [B, S, 3]");
  const bool masked = source_valid_in.numel() > 0;
  const at::Tensor source_valid = masked ? source_valid_in.to(at::kBool).contiguous() : source_valid_in;
  TORCH_CHECK(!masked || source_valid.sizes() == at::IntArrayRef({batch, height, width}), "plane_sweep_volume: expected masks [B, H, W]");
  at::Tensor cost = at::empty({batch, slots, planes, height, width}, features.options());
  at::Tensor share = at::empty({batch, slots, height, width}, features.options());
  at::Tensor parallax = at::empty({batch, slots, height, width}, features.options());
  at::Tensor valid = at::empty({batch, slots, planes, height, width}, features.options().dtype(at::kBool));
  bool* o_valid = valid.data_ptr<bool>();
  const float* feat = features.data_ptr<float>();
  const float* ray = rays.data_ptr<float>();
  const float* pa = a.data_ptr<float>();
  const float* pb = b.data_ptr<float>();
  const int64_t* src = sources.data_ptr<int64_t>();
  const float* dep = depths.data_ptr<float>();
  const bool* mask = masked ? source_valid.data_ptr<bool>() : nullptr;
  float* o_cost = cost.data_ptr<float>();
  float* o_share = share.data_ptr<float>();
  float* o_par = parallax.data_ptr<float>();
  const int64_t pixels = height * width, image = pixels * channels;
  const float zmin = static_cast<float>(min_z);
  at::parallel_for(0, batch * slots * height, 1, [&](int64_t begin, int64_t end) {
    std::vector<float> sampled(channels);
    float* vec = sampled.data();
    for (int64_t job = begin; job < end; ++job) {
      const int64_t b_ = job / (slots * height), s = (job / height) % slots, row = job % height;
      const int64_t source = src[b_ * slots + s];
      if (source < 0) {  // no source: nothing valid, no cost, no parallax
        for (int64_t col = 0; col < width; ++col) {
          const int64_t i = row * width + col;
          for (int64_t p = 0; p < planes; ++p) {
            o_valid[((b_ * slots + s) * planes + p) * pixels + i] = false;
            o_cost[((b_ * slots + s) * planes + p) * pixels + i] = 0.0f;
          }
          o_share[(b_ * slots + s) * pixels + i] = 0.0f;
          o_par[(b_ * slots + s) * pixels + i] = 0.0f;
        }
        continue;
      }
      const float* am = pa + (b_ * slots + s) * 9;
      const float* bv = pb + (b_ * slots + s) * 3;
      const float* other = feat + source * image;
      const bool* smask = masked ? mask + source * pixels : nullptr;
      for (int64_t col = 0; col < width; ++col) {
        const int64_t i = row * width + col;
        float* cost_at = o_cost + (b_ * slots + s) * planes * pixels + i;  // + p * pixels
        const float* r = ray + (b_ * pixels + i) * 3;
        const float ar[3] = {am[0] * r[0] + am[1] * r[1] + am[2] * r[2], am[3] * r[0] + am[4] * r[1] + am[5] * r[2],
                             am[6] * r[0] + am[7] * r[1] + am[8] * r[2]};
        const float* t = feat + b_ * image + i * channels;
        float count = 0.0f, path = 0.0f, last_u = 0.0f, last_v = 0.0f;
        bool last_ok = false;
        for (int64_t p = 0; p < planes; ++p) {
          const float d = dep[p];
          const float hz = d * ar[2] + bv[2];
          const float zc = std::max(hz, 1e-6f);
          const float u = (d * ar[0] + bv[0]) / zc, v = (d * ar[1] + bv[1]) / zc;
          bool ok = hz > zmin && u >= 0.0f && u <= width - 1 && v >= 0.0f && v <= height - 1;
          if (ok && smask != nullptr) {
            const int64_t cu = static_cast<int64_t>(std::nearbyint(u)), cv = static_cast<int64_t>(std::nearbyint(v));
            ok = smask[cv * width + cu];
          }
          o_valid[((b_ * slots + s) * planes + p) * pixels + i] = ok;
          if (!ok) {
            cost_at[p * pixels] = 0.0f;
          } else {
            cost_at[p * pixels] = interpolated_dot(other, t, taps_of(u, v), height, width, channels, vec);
            count += 1.0f;
            if (last_ok) path += std::sqrt((u - last_u) * (u - last_u) + (v - last_v) * (v - last_v));
          }
          last_ok = ok;
          last_u = u;
          last_v = v;
        }
        o_share[(b_ * slots + s) * pixels + i] = count / static_cast<float>(planes);
        o_par[(b_ * slots + s) * pixels + i] = path;
      }
    }
  });
  return {cost, share, parallax, valid};
}

// see_through_votes: free-space carving (drivingscene.gaussians.visibility.see_through_votes). For
// each Gaussian n and each other image j (of its own keyframe only when same_time): its centre at
// time t_j (means + s flows, s = t_j for keyframe-0 Gaussians and 1 - t_j for keyframe-1 ones),
// projected into j; a vote when z > 0.1, the nearest pixel (rounded half to even, as torch.round)
// is inside the image, j's depth there is a vote (< no_depth) and z < (1 - margin) depth.
at::Tensor see_through_votes(const at::Tensor& means_in, const at::Tensor& flows_in, const at::Tensor& keyframes_in,
                             const at::Tensor& image_ids_in, const at::Tensor& world_to_cam_in, const at::Tensor& intrinsics_in,
                             const at::Tensor& depths_in, const at::Tensor& times_in, double margin, bool same_time,
                             double no_depth) {
  const at::Tensor means = means_in.to(at::kFloat).contiguous();
  const at::Tensor flows = flows_in.to(at::kFloat).contiguous();
  const at::Tensor keyframes = keyframes_in.to(at::kLong).contiguous();
  const at::Tensor ids = image_ids_in.to(at::kLong).contiguous();
  const at::Tensor w2c = world_to_cam_in.to(at::kFloat).contiguous();
  const at::Tensor k = intrinsics_in.to(at::kFloat).contiguous();
  const at::Tensor depths = depths_in.to(at::kFloat).contiguous();
  const at::Tensor times = times_in.to(at::kFloat).contiguous();
  const int64_t n = means.size(0), images = depths.size(0), height = depths.size(1), width = depths.size(2);
  TORCH_CHECK(means.dim() == 2 && means.size(1) == 3 && flows.sizes() == means.sizes(), "see_through_votes: expected means, flows [N, 3]");
  TORCH_CHECK(keyframes.size(0) == n && ids.size(0) == n, "see_through_votes: expected keyframes, image_ids [N]");
  TORCH_CHECK(w2c.size(0) == images && k.size(0) == images && times.size(0) == images, "see_through_votes: one pose per image");
  at::Tensor votes = at::zeros({n}, means.options().dtype(at::kInt));
  const float* m = means.data_ptr<float>();
  const float* f = flows.data_ptr<float>();
  const int64_t* kf = keyframes.data_ptr<int64_t>();
  const int64_t* id = ids.data_ptr<int64_t>();
  const float* pose = w2c.data_ptr<float>();
  const float* intr = k.data_ptr<float>();
  const float* dep = depths.data_ptr<float>();
  const float* tt = times.data_ptr<float>();
  int32_t* out = votes.data_ptr<int32_t>();
  const int64_t per_time = images / 2;
  const float keep = static_cast<float>(1.0 - margin), none = static_cast<float>(no_depth);
  at::parallel_for(0, n, 4096, [&](int64_t begin, int64_t end) {
    for (int64_t i = begin; i < end; ++i) {
      int32_t count = 0;
      for (int64_t j = 0; j < images; ++j) {
        if (j == id[i] || (same_time && j / per_time != id[i] / per_time)) continue;
        const float step = kf[i] == 0 ? tt[j] : 1.0f - tt[j];
        const float x = m[3 * i] + step * f[3 * i], y = m[3 * i + 1] + step * f[3 * i + 1], z = m[3 * i + 2] + step * f[3 * i + 2];
        const float* r = pose + 16 * j;
        const float cz = r[8] * x + r[9] * y + r[10] * z + r[11];
        if (!(cz > 0.1f)) continue;
        const float cx = r[0] * x + r[1] * y + r[2] * z + r[3], cy = r[4] * x + r[5] * y + r[6] * z + r[7];
        const float* q = intr + 9 * j;
        const float inv = 1.0f / cz;
        const float u = q[0] * cx * inv + q[1] * cy * inv + q[2], v = q[4] * cy * inv + q[5];
        const float cu = std::nearbyint(u), cv = std::nearbyint(v);
        if (!(cu >= 0.0f && cu < width && cv >= 0.0f && cv < height)) continue;
        const float seen = dep[(j * height + static_cast<int64_t>(cv)) * width + static_cast<int64_t>(cu)];
        if (seen < none && cz < keep * seen) ++count;
      }
      out[i] = count;
    }
  });
  return votes;
}

TORCH_LIBRARY_FRAGMENT(drivingscene_render, m) {
  m.def("see_through_votes(Tensor means, Tensor flows, Tensor keyframes, Tensor image_ids, Tensor world_to_cam, "
        "Tensor intrinsics, Tensor depths, Tensor times, float margin, bool same_time, float no_depth) -> Tensor",
        &see_through_votes);
  m.def("plane_sweep_volume(Tensor features, Tensor rays, Tensor a, Tensor b, Tensor sources, Tensor depths, "
        "Tensor source_valid, float min_z) -> Tensor[]",
        &plane_sweep_volume);
  m.def("plane_sweep_correlate(Tensor features, Tensor sources, Tensor uv, Tensor valid) -> Tensor", &plane_sweep_correlate);
  m.def("plane_sweep_correlate_backward(Tensor features, Tensor sources, Tensor uv, Tensor valid, Tensor grad) -> Tensor",
        &plane_sweep_correlate_backward);
}
