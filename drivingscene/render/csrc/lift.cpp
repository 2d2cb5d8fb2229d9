// Lifting optical flow to scene flow at every pixel (the optional compiled path of the dense
// branch of drivingscene.models.pipeline.lift_scene_flow), one pass per pixel instead of ~40
// full-image tensor operations.
//
// For a pixel p of the source keyframe with flow f(p) to the other keyframe:
//   q = p + f(p); the destination depth is the other keyframe's depth at the nearest pixel of q
//   (rounded half to even, as torch.round); valid: q's nearest pixel inside the image and both
//   depths positive (geometry.scene_flow.scene_flow_from_optical_flow);
//   scene flow = dst_cam_to_world * unproject(q, d_dst) - src_cam_to_world * unproject(p, d_src);
//   consistent: the backward flow b sampled bilinearly at q (border-clamped, as grid_sample with
//   align_corners=True) undoes f, |f + b(q)|^2 < alpha (|f|^2 + |b(q)|^2) + beta, and q inside
//   [-0.5, W - 0.5] x [-0.5, H - 0.5] (geometry.flow.forward_backward_consistency);
//   dynamic = candidate & valid & consistent; the scene flow is 0 where the pixel is not dynamic.
// The arithmetic is float32 like the torch path's, in another order (sums of products): the same
// result up to float rounding (the tests compare them).
#include <ATen/ATen.h>
#include <ATen/Parallel.h>
#include <torch/library.h>

#include <algorithm>
#include <cmath>

namespace {

std::tuple<at::Tensor, at::Tensor> lift_dense(const at::Tensor& depth_src_in, const at::Tensor& depth_dst_in,
                                              const at::Tensor& flow_in, const at::Tensor& flow_back_in,
                                              const at::Tensor& candidate_in, const at::Tensor& intrinsics_in,
                                              const at::Tensor& src_to_world_in, const at::Tensor& dst_to_world_in,
                                              double alpha, double beta) {
  TORCH_CHECK(depth_src_in.dim() == 3, "lift_dense: expected depth [V, H, W]");
  const int64_t views = depth_src_in.size(0), height = depth_src_in.size(1), width = depth_src_in.size(2);
  TORCH_CHECK(depth_dst_in.sizes() == depth_src_in.sizes(), "lift_dense: expected both depths [V, H, W]");
  TORCH_CHECK(flow_in.dim() == 4 && flow_in.size(0) == views && flow_in.size(1) == height && flow_in.size(2) == width &&
                  flow_in.size(3) == 2 && flow_back_in.sizes() == flow_in.sizes(),
              "lift_dense: expected both flows [V, H, W, 2]");
  TORCH_CHECK(candidate_in.sizes() == depth_src_in.sizes(), "lift_dense: expected candidate [V, H, W]");
  TORCH_CHECK(intrinsics_in.dim() == 3 && intrinsics_in.size(0) == views, "lift_dense: expected intrinsics [V, 3, 3]");
  TORCH_CHECK(src_to_world_in.dim() == 3 && src_to_world_in.size(0) == views && dst_to_world_in.sizes() == src_to_world_in.sizes(),
              "lift_dense: expected transforms [V, 4, 4]");
  const at::Tensor depth_src = depth_src_in.to(at::kFloat).contiguous();
  const at::Tensor depth_dst = depth_dst_in.to(at::kFloat).contiguous();
  const at::Tensor flow = flow_in.to(at::kFloat).contiguous();
  const at::Tensor flow_back = flow_back_in.to(at::kFloat).contiguous();
  const at::Tensor candidate = candidate_in.to(at::kBool).contiguous();
  const at::Tensor intrinsics = intrinsics_in.to(at::kFloat).contiguous();
  const at::Tensor src_to_world = src_to_world_in.to(at::kFloat).contiguous();
  const at::Tensor dst_to_world = dst_to_world_in.to(at::kFloat).contiguous();
  at::Tensor scene_flow = at::empty({views, height, width, 3}, depth_src.options());
  at::Tensor dynamic = at::empty({views, height, width}, candidate.options());
  const float* ds = depth_src.data_ptr<float>();
  const float* dd = depth_dst.data_ptr<float>();
  const float* fw = flow.data_ptr<float>();
  const float* bw = flow_back.data_ptr<float>();
  const bool* cand = candidate.data_ptr<bool>();
  const float* kk = intrinsics.data_ptr<float>();
  const float* ts = src_to_world.data_ptr<float>();
  const float* td = dst_to_world.data_ptr<float>();
  float* out = scene_flow.data_ptr<float>();
  bool* dyn = dynamic.data_ptr<bool>();
  const int64_t pixels = height * width;
  const float a = static_cast<float>(alpha), b = static_cast<float>(beta);
  const float x_max = static_cast<float>(width - 1), y_max = static_cast<float>(height - 1);
  const int64_t x0_max = std::max(width - 2, int64_t{0}), y0_max = std::max(height - 2, int64_t{0});

  at::parallel_for(0, views * height, 16, [&](int64_t begin, int64_t end) {
    for (int64_t vr = begin; vr < end; ++vr) {
      const int64_t v = vr / height, row = vr % height;
      const float* k = kk + 9 * v;
      const float fx = k[0], skew = k[1], cx = k[2], fy = k[4], cy = k[5];
      const float* ms = ts + 16 * v;
      const float* md = td + 16 * v;
      const float* back = bw + v * pixels * 2;
      const float* depth_here = dd + v * pixels;
      for (int64_t col = 0; col < width; ++col) {
        const int64_t i = vr * width + col;
        float* sf = out + 3 * i;
        sf[0] = sf[1] = sf[2] = 0.0f;
        dyn[i] = false;
        if (!cand[i]) continue;
        const float f0 = fw[2 * i], f1 = fw[2 * i + 1];
        const float u = static_cast<float>(col) + f0, w = static_cast<float>(row) + f1;
        // forward/backward consistency, with b sampled bilinearly at q
        if (!(u >= -0.5f && u <= width - 0.5f && w >= -0.5f && w <= height - 0.5f)) continue;
        const float xc = std::min(std::max(u, 0.0f), x_max), yc = std::min(std::max(w, 0.0f), y_max);
        const int64_t x0 = std::min(static_cast<int64_t>(xc), x0_max), y0 = std::min(static_cast<int64_t>(yc), y0_max);
        const int64_t dx = x0 + 1 < width ? 2 : 0, dy = y0 + 1 < height ? 2 * width : 0;
        const float wx = xc - static_cast<float>(x0), wy = yc - static_cast<float>(y0);
        const float* s = back + 2 * (y0 * width + x0);
        float bq[2];
        for (int c = 0; c < 2; ++c) {
          const float top = s[c] * (1.0f - wx) + s[dx + c] * wx;
          const float bottom = s[dy + c] * (1.0f - wx) + s[dy + dx + c] * wx;
          bq[c] = top * (1.0f - wy) + bottom * wy;
        }
        const float e0 = f0 + bq[0], e1 = f1 + bq[1];
        if (!(e0 * e0 + e1 * e1 < a * ((f0 * f0 + f1 * f1) + (bq[0] * bq[0] + bq[1] * bq[1])) + b)) continue;
        // the scene flow from the nearest destination pixel's depth
        const int64_t qc = static_cast<int64_t>(std::nearbyint(u)), qr = static_cast<int64_t>(std::nearbyint(w));
        if (qc < 0 || qc >= width || qr < 0 || qr >= height) continue;
        const float d_src = ds[i], d_dst = depth_here[qr * width + qc];
        if (!(d_src > 0.0f && d_dst > 0.0f)) continue;
        const float ys = (static_cast<float>(row) - cy) / fy;
        const float xs = (static_cast<float>(col) - cx - skew * ys) / fx;
        const float yd = (w - cy) / fy;
        const float xd = (u - cx - skew * yd) / fx;
        const float p[3] = {xs * d_src, ys * d_src, d_src}, q[3] = {xd * d_dst, yd * d_dst, d_dst};
        for (int r = 0; r < 3; ++r) {
          const float to = md[4 * r + 3] + md[4 * r] * q[0] + md[4 * r + 1] * q[1] + md[4 * r + 2] * q[2];
          const float from = ms[4 * r + 3] + ms[4 * r] * p[0] + ms[4 * r + 1] * p[1] + ms[4 * r + 2] * p[2];
          sf[r] = to - from;
        }
        dyn[i] = true;
      }
    }
  });
  return {scene_flow, dynamic};
}

}  // namespace

TORCH_LIBRARY_FRAGMENT(drivingscene_render, m) {
  m.def("lift_dense(Tensor depth_src, Tensor depth_dst, Tensor flow, Tensor flow_back, Tensor candidate, Tensor intrinsics, "
        "Tensor src_to_world, Tensor dst_to_world, float alpha, float beta) -> (Tensor, Tensor)",
        &lift_dense);
}
