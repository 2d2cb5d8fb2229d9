// Front-to-back compositing over the rasterizer's pair buffer, forward and backward (the compiled
// path of drivingscene.render.composite._Composite; composite_torch and composite_backward_torch
// there are the reference).
//
// Each pixel p (global over cameras: p = (b H + y) W + x) has up to L splat ids in
// pair_ids[p, :] (front to back, -1 where empty). A splat's row of `packed` holds
// mean x, mean y, conic a, b, c, opacity, z and C colour channels. Per pixel, with
// d = (x - mean x, y - mean y):
//
//     sigma = 0.5 (a dx^2 + c dy^2) + b dx dy,  raw = opacity exp(-sigma),  alpha = min(raw, 0.99)
//     w_k = alpha_k T_k,  T_{k+1} = T_k (1 - alpha_k),  T_0 = 1
//     rgb = sum w c + T_L bg[b],  S = sum w,  depth = sum w z / S (0 where S < 1e-6)
//
// Surface averaging (tolerance tau > 0; EWA surface splatting's depth tolerance): the front
// group F, the first listed splat and those after it with z <= z_0 (1 + tau) (a prefix: the list
// is in depth order), is averaged instead of composited,
//     w_i = A alpha_i / S_F  (i in F),  A = 1 - P,  P = prod_F (1 - alpha_i),  S_F = sum_F alpha_i
// and the splats behind it are composited as above with T starting at P. tau = 0: F is the first
// splat alone, which is plain compositing. The accumulated alpha is 1 - prod (1 - alpha) either way.
//
// Backward (v_k = dL/dw_k; Kerbl et al. 2023, supplementary), behind F:
//     dL/dalpha_k = v_k T_k - (sum_{j>k} v_j w_j + (dL/drgb . bg) T_L) / (1 - alpha_k)
// and in F, with M = sum_F v_i alpha_i / S_F and B = sum_{j behind F} v_j w_j + (dL/drgb . bg) T_L:
//     dL/dalpha_k = (A / S_F) (v_k - M) + (M P - B) / (1 - alpha_k)
// with no gradient through alpha where raw > 0.99 (the clamp). The pair finder already applied
// the cut, the early stop and the layer cap: every listed splat contributes.
//
// A splat id beyond packed's rows is an error, never a read outside it. Pixels are split between
// threads in contiguous ranges; the gradients of the splat rows go to one buffer per thread
// (several pixels share a splat), summed at the end, as are the background's. The same operations
// as the torch path, sums in another order (float rounding; the tests compare both).
#include <ATen/ATen.h>
#include <ATen/Parallel.h>
#include <torch/library.h>

#include "front_group.h"

#include <algorithm>
#include <atomic>
#include <cmath>
#include <vector>

namespace {

using drivingscene_front::front_weights;
using drivingscene_front::FrontWeights;
using drivingscene_front::joins_front;

constexpr float kMaxAlpha = 0.99f;
constexpr float kMinWeightSum = 1e-6f;
constexpr int64_t kFixed = 7;  // mean x, mean y, conic a, b, c, opacity, z

struct Inputs {
  at::Tensor packed, backgrounds, ids;
  int64_t pixels, layers, rows, row, channels, cameras;
};

Inputs check(const char* name, const at::Tensor& packed_in, const at::Tensor& backgrounds_in, const at::Tensor& ids_in,
             int64_t width, int64_t height) {
  TORCH_CHECK(packed_in.dim() == 2 && packed_in.size(1) > kFixed, name, ": expected packed [M, 7 + C]");
  TORCH_CHECK(backgrounds_in.dim() == 2 && backgrounds_in.size(1) == packed_in.size(1) - kFixed, name,
              ": expected backgrounds [B, C] with the C of packed");
  TORCH_CHECK(ids_in.dim() == 2, name, ": expected pair_ids [P, L]");
  TORCH_CHECK(width > 0 && height > 0 && ids_in.size(0) == backgrounds_in.size(0) * width * height, name,
              ": expected P = B * H * W pixels");
  Inputs c{packed_in.to(at::kFloat).contiguous(), backgrounds_in.to(at::kFloat).contiguous(), ids_in.to(at::kInt).contiguous(),
           ids_in.size(0), ids_in.size(1), packed_in.size(0), packed_in.size(1), packed_in.size(1) - kFixed, backgrounds_in.size(0)};
  return c;
}

}  // namespace

std::vector<at::Tensor> composite_forward(const at::Tensor& packed_in, const at::Tensor& backgrounds_in, const at::Tensor& pair_ids,
                                          int64_t width, int64_t height, double tolerance) {
  const Inputs c = check("composite_forward", packed_in, backgrounds_in, pair_ids, width, height);
  at::Tensor rgb = at::empty({c.pixels, c.channels}, c.packed.options());
  at::Tensor depth = at::empty({c.pixels}, c.packed.options());
  at::Tensor weight_sum = at::empty({c.pixels}, c.packed.options());
  const float* packed = c.packed.data_ptr<float>();
  const float* bgs = c.backgrounds.data_ptr<float>();
  const int32_t* ids = c.ids.data_ptr<int32_t>();
  float* o_rgb = rgb.data_ptr<float>();
  float* o_depth = depth.data_ptr<float>();
  float* o_ws = weight_sum.data_ptr<float>();
  const int64_t layers = c.layers, row = c.row, channels = c.channels, image = width * height, rows = c.rows;
  std::atomic<bool> out_of_range{false};
  const float tol = static_cast<float>(tolerance);
  at::parallel_for(0, c.pixels, 1024, [&](int64_t begin, int64_t end) {
    std::vector<float> acc(channels), front(channels);
    for (int64_t p = begin; p < end; ++p) {
      const float u = static_cast<float>(p % width), v = static_cast<float>((p / width) % height);
      std::fill(acc.begin(), acc.end(), 0.0f);
      std::fill(front.begin(), front.end(), 0.0f);
      float trans = 1.0f, ws = 0.0f, wz = 0.0f;
      // the front group: alpha sum, transmittance through it, sum alpha z; open until a splat beyond it
      float f_sum = 0.0f, f_trans = 1.0f, f_z = 0.0f, z_limit = 0.0f;
      int64_t f_count = 0;
      bool in_front = true;
      auto close_front = [&]() {  // the group's average, weighted by its coverage A = 1 - P
        const FrontWeights fw = front_weights(f_count, f_sum, f_trans);
        for (int64_t ch = 0; ch < channels; ++ch) acc[ch] = front[ch] * fw.scale;
        ws = fw.cover;
        wz = f_z * fw.scale;
        trans = f_trans;
        in_front = false;
      };
      for (int64_t k = 0; k < layers; ++k) {
        const int32_t id = ids[p * layers + k];
        if (id < 0) continue;
        if (id >= rows) {
          out_of_range = true;
          continue;
        }
        const float* r = packed + static_cast<int64_t>(id) * row;
        const float dx = u - r[0], dy = v - r[1];
        const float sigma = 0.5f * (r[2] * dx * dx + r[4] * dy * dy) + r[3] * dx * dy;
        const float alpha = std::min(r[5] * std::exp(-sigma), kMaxAlpha);
        if (in_front && joins_front(f_count, tol, r[6], z_limit)) {
          if (f_count == 0) z_limit = r[6] * (1.0f + tol);
          ++f_count;
          f_sum += alpha;
          f_trans *= 1.0f - alpha;
          f_z += alpha * r[6];
          for (int64_t ch = 0; ch < channels; ++ch) front[ch] += alpha * r[kFixed + ch];
          continue;
        }
        if (in_front) {
          close_front();
        }
        const float w = alpha * trans;
        trans = trans * (1.0f - alpha);
        ws += w;
        wz += w * r[6];
        for (int64_t ch = 0; ch < channels; ++ch) acc[ch] += w * r[kFixed + ch];
      }
      if (in_front && f_count > 0) close_front();
      const float* bg = bgs + (p / image) * channels;
      for (int64_t ch = 0; ch < channels; ++ch) o_rgb[p * channels + ch] = acc[ch] + trans * bg[ch];
      o_ws[p] = ws;
      o_depth[p] = ws >= kMinWeightSum ? wz / ws : 0.0f;
    }
  });
  TORCH_CHECK(!out_of_range, "composite_forward: pair_ids refer to splats beyond the ", rows, " rows of packed");
  return {rgb, depth, weight_sum};
}

std::vector<at::Tensor> composite_backward(const at::Tensor& packed_in, const at::Tensor& backgrounds_in, const at::Tensor& pair_ids,
                                           int64_t width, int64_t height, const at::Tensor& depth_in, const at::Tensor& weight_sum_in,
                                           const at::Tensor& grad_rgb_in, const at::Tensor& grad_depth_in,
                                           const at::Tensor& grad_alpha_in, double tolerance) {
  const Inputs c = check("composite_backward", packed_in, backgrounds_in, pair_ids, width, height);
  const at::Tensor depth = depth_in.to(at::kFloat).contiguous(), weight_sum = weight_sum_in.to(at::kFloat).contiguous();
  const at::Tensor grad_rgb = grad_rgb_in.to(at::kFloat).contiguous();
  const at::Tensor grad_depth = grad_depth_in.to(at::kFloat).contiguous(), grad_alpha = grad_alpha_in.to(at::kFloat).contiguous();
  TORCH_CHECK(depth.numel() == c.pixels && weight_sum.numel() == c.pixels && grad_depth.numel() == c.pixels &&
                  grad_alpha.numel() == c.pixels && grad_rgb.numel() == c.pixels * c.channels,
              "composite_backward: expected depth, weight_sum, grad_depth, grad_alpha [P] and grad_rgb [P, C]");
  const int64_t layers = c.layers, row = c.row, channels = c.channels, image = width * height, rows = c.rows;
  std::atomic<bool> out_of_range{false};
  const int threads = std::max(1, at::get_num_threads());
  // One slice per thread: the splat rows' gradients, then the backgrounds'.
  const int64_t slice = c.rows * row + c.cameras * channels;
  at::Tensor buffers = at::zeros({threads, slice}, c.packed.options());
  const float* packed = c.packed.data_ptr<float>();
  const float* bgs = c.backgrounds.data_ptr<float>();
  const int32_t* ids = c.ids.data_ptr<int32_t>();
  const float* dep = depth.data_ptr<float>();
  const float* wsum = weight_sum.data_ptr<float>();
  const float* g_rgb = grad_rgb.data_ptr<float>();
  const float* g_depth = grad_depth.data_ptr<float>();
  const float* g_alpha = grad_alpha.data_ptr<float>();
  float* base = buffers.data_ptr<float>();
  const float tol = static_cast<float>(tolerance);
  at::parallel_for(0, c.pixels, 1024, [&](int64_t begin, int64_t end) {
    float* grads = base + at::get_thread_num() * slice;
    float* grad_bg = grads + c.rows * row;
    // per layer of one pixel: alpha, transmittance before it, its weight, raw, exp(-sigma), dx, dy, v
    std::vector<float> alpha(layers), before(layers), weight(layers), raw(layers), e(layers), ddx(layers), ddy(layers), vk(layers);
    for (int64_t p = begin; p < end; ++p) {
      const float u = static_cast<float>(p % width), v = static_cast<float>((p / width) % height);
      const float* gr = g_rgb + p * channels;
      const float* bg = bgs + (p / image) * channels;
      const bool has = wsum[p] >= kMinWeightSum;
      const float grad_d = has ? g_depth[p] / wsum[p] : 0.0f;
      // The front group (module comment): the listed splats k < f_end with z <= z_0 (1 + tol).
      int64_t f_end = 0, f_count = 0;
      float f_sum = 0.0f, f_trans = 1.0f, z_limit = 0.0f;
      bool in_front = true;
      float trans = 1.0f;
      for (int64_t k = 0; k < layers; ++k) {
        const int32_t id = ids[p * layers + k];
        if (id >= rows) out_of_range = true;
        if (id < 0 || id >= rows) {
          alpha[k] = 0.0f;
          before[k] = trans;
          weight[k] = 0.0f;
          vk[k] = 0.0f;
          if (in_front) f_end = k + 1;
          continue;
        }
        const float* r = packed + static_cast<int64_t>(id) * row;
        const float dx = u - r[0], dy = v - r[1];
        e[k] = std::exp(-(0.5f * (r[2] * dx * dx + r[4] * dy * dy) + r[3] * dx * dy));
        raw[k] = r[5] * e[k];
        alpha[k] = std::min(raw[k], kMaxAlpha);
        ddx[k] = dx;
        ddy[k] = dy;
        float vv = g_alpha[p] + grad_d * (r[6] - dep[p]);
        for (int64_t ch = 0; ch < channels; ++ch) vv = vv + gr[ch] * r[kFixed + ch];
        vk[k] = vv;
        if (in_front && joins_front(f_count, tol, r[6], z_limit)) {
          if (f_count == 0) z_limit = r[6] * (1.0f + tol);
          ++f_count;
          f_sum += alpha[k];
          f_trans *= 1.0f - alpha[k];
          f_end = k + 1;
          continue;
        }
        if (in_front) {  // the group closes: its weights, then plain compositing behind it
          in_front = false;
          trans = f_trans;
        }
        before[k] = trans;
        weight[k] = alpha[k] * trans;
        trans = trans * (1.0f - alpha[k]);
      }
      if (in_front) trans = f_trans;
      const float scale = front_weights(f_count, f_sum, f_trans).scale;
      float mean_v = 0.0f;  // M = sum_F v alpha / S_F
      for (int64_t k = 0; k < f_end; ++k) {
        weight[k] = alpha[k] * scale;
        before[k] = 1.0f;
        mean_v += vk[k] * alpha[k];
      }
      mean_v = f_sum > 0.0f ? mean_v / f_sum : 0.0f;
      float bg_dot = 0.0f;
      for (int64_t ch = 0; ch < channels; ++ch) {
        bg_dot += gr[ch] * bg[ch];
        grad_bg[(p / image) * channels + ch] += gr[ch] * trans;
      }
      float behind = bg_dot * trans;  // sum over j > k of v_j w_j, plus the background's share
      float behind_front = 0.0f;      // B: the same sum for the front group (everything behind it)
      for (int64_t k = layers - 1; k >= 0; --k) {
        if (k == f_end - 1) behind_front = behind;
        const int32_t id = ids[p * layers + k];
        if (id < 0 || id >= rows) continue;
        const float* r = packed + static_cast<int64_t>(id) * row;
        float* g = grads + static_cast<int64_t>(id) * row;
        float grad_alpha_k;
        if (k >= f_end) {
          grad_alpha_k = vk[k] * before[k] - behind / (1.0f - alpha[k]);
          behind += vk[k] * weight[k];
        } else if (f_count == 1) {  // plain compositing's formula (T = 1), exactly
          grad_alpha_k = vk[k] - behind_front / (1.0f - alpha[k]);
        } else {
          grad_alpha_k = scale * (vk[k] - mean_v) + (mean_v * f_trans - behind_front) / (1.0f - alpha[k]);
        }
        if (raw[k] <= kMaxAlpha) {  // else alpha is clamped: no gradient through it (nor 0 * inf)
          const float grad_raw = grad_alpha_k;
          const float grad_sigma = -grad_raw * raw[k];
          const float dx = ddx[k], dy = ddy[k];
          g[0] += -grad_sigma * (r[2] * dx + r[3] * dy);
          g[1] += -grad_sigma * (r[3] * dx + r[4] * dy);
          g[2] += 0.5f * grad_sigma * dx * dx;
          g[3] += grad_sigma * dx * dy;
          g[4] += 0.5f * grad_sigma * dy * dy;
          g[5] += grad_raw * e[k];
        }
        g[6] += weight[k] * grad_d;
        for (int64_t ch = 0; ch < channels; ++ch) g[kFixed + ch] += weight[k] * gr[ch];
      }
    }
  });
  TORCH_CHECK(!out_of_range, "composite_backward: pair_ids refer to splats beyond the ", rows, " rows of packed");
  const at::Tensor total = buffers.sum(0);
  return {total.narrow(0, 0, c.rows * row).view({c.rows, row}), total.narrow(0, c.rows * row, c.cameras * channels).view({c.cameras, channels})};
}

TORCH_LIBRARY_FRAGMENT(drivingscene_render, m) {
  m.def("composite_forward(Tensor packed, Tensor backgrounds, Tensor pair_ids, int width, int height, float tolerance) -> Tensor[]",
        &composite_forward);
  m.def("composite_backward(Tensor packed, Tensor backgrounds, Tensor pair_ids, int width, int height, Tensor depth, "
        "Tensor weight_sum, Tensor grad_rgb, Tensor grad_depth, Tensor grad_alpha, float tolerance) -> Tensor[]",
        &composite_backward);
}
