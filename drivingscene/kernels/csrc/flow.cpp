// Flow kernels at inference: the photometric search along the rigid flow (the optional compiled
// path of drivingscene.geometry.flow_search.search_along_rigid), the local cost volume of the
// residual flow network (drivingscene.models.residual_flow.local_cost_volume) and the dense lift of
// optical flow to scene flow (the dense branch of drivingscene.models.pipeline.lift_scene_flow).
//
// search_along_rigid: per image, one pass per hypothesis over the pixels: sample the other image
// bilinearly (border-clamped, as grid_sample with align_corners=True and padding "border") at
// p + flow, mean absolute difference over channels, a sample outside the image costs
// `outside_cost`; the cost image is box-filtered (window cut at the border, the mean over the
// positions inside), the hypothesis' bonus subtracted, and the running minimum kept (strictly
// lower wins: the first of exact ties). The torch path warps every hypothesis as a full image
// and filters with cumulative sums; both pick the same hypothesis up to float rounding (tests).
//
// local_cost_volume: mean over channels of target * source shifted by (dx, dy) in [-r, r]^2,
// zero outside; the same arithmetic as the torch path up to the order of the channel sum.
//
// lift_dense: one pass per pixel instead of ~40 full-image tensor operations.
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
//
// epipolar_parallax: for each pixel p of one keyframe with flow f(p) to the same camera at the other
// keyframe (drivingscene.models.pipeline.epipolar_geometry, the torch path): the ray a = R K^-1 p in
// the other camera's axes, the end point x = K^-1 (p + f), the depth z along the ray whose image is
// nearest x in the least-squares sense over both image axes, its image proj = K (z a + t), the
// distance of proj from p + f (off the epipolar line), its offset from K a (the point at infinite
// depth: the parallax, a vector), and valid: z a + t in front (z > near_z), a_z > 0, p + f inside
// [0, W - 1] x [0, H - 1] and z finite. One pass per pixel instead of ~25 full-image tensor operations.
//
// rigid_flow_dense: the flow of a static world (drivingscene.geometry.flow.rigid_flow): each pixel
// lifted with its z-depth (geometry.camera.unproject), moved by src_to_dst (se3.transform_points:
// t + x r0 + y r1 + z r2, in that order) and projected with the destination intrinsics
// (camera.project, z clamped at 1e-6); the same float32 operations in the same order as the torch
// path, one pass per pixel.
//
// rig_stereo: the checks and the triangulation of one pair of overlapping cameras a, b of one keyframe
// (drivingscene.methods.cross_camera, the numpy path `_stereo_numpy`), per pixel p of a's box:
// q = end(p), its match in b; consistent: b's match back at q's nearest pixel of b's box (rounded
// half to even, as numpy.rint) lands within `consistency_px` of p; q's nearest pixel inside b and one
// of b's world pixels; p one of a's world pixels; then two-camera triangulation with each camera's
// intrinsics: the ray a = M (p, 1) in b's axes (M = R K_a^-1), the end point x = K_b^-1 (q, 1), the
// depth z along the ray whose image is nearest x (least squares over both image axes), its image
// proj = K_b (z a + t), off the line |proj - q|, parallax |proj - K_b a| (the point at infinite depth);
// determined: in front (z a + t beyond near_z, a_z > 0, z finite), off the line at most epipolar_px,
// parallax at least min_parallax, z within [z_near, z_far]. Output: z and the parallax, 0 where not
// determined. Float32 like the numpy path, in another order: the same up to float rounding (tests).
//
// fb_consistent: forward/backward consistency (geometry.flow.forward_backward_consistency), the test
// of lift_dense above on its own: b sampled bilinearly at q = p + f(p) (border-clamped),
// |f + b(q)|^2 < alpha (|f|^2 + |b(q)|^2) + beta and q inside [-0.5, W - 0.5] x [-0.5, H - 0.5].
#include <ATen/ATen.h>
#include <ATen/Parallel.h>
#include <torch/library.h>

#include <algorithm>
#include <cmath>
#include <limits>
#include <vector>

namespace {

// Whether the point (x, y) falls inside the image (geometry.flow.inside_image).
inline bool inside_image(float x, float y, int64_t height, int64_t width) {
  return x >= -0.5f && x <= width - 0.5f && y >= -0.5f && y <= height - 0.5f;
}

// Where and how to sample (x, y) bilinearly, border-clamped as grid_sample with align_corners=True:
// the top-left pixel (x0, y0), whether it has a right and a lower neighbour (1) or not (0), and
// the weights of those neighbours.
struct BilinearTap {
  int64_t x0, y0, right, below;
  float wx, wy;
};

inline BilinearTap bilinear_tap(float x, float y, int64_t height, int64_t width) {
  const float xc = std::min(std::max(x, 0.0f), static_cast<float>(width - 1));
  const float yc = std::min(std::max(y, 0.0f), static_cast<float>(height - 1));
  const int64_t x0 = std::min(static_cast<int64_t>(xc), std::max(width - 2, int64_t{0}));  // xc >= 0: truncation is floor
  const int64_t y0 = std::min(static_cast<int64_t>(yc), std::max(height - 2, int64_t{0}));
  return {x0, y0, x0 + 1 < width ? 1 : 0, y0 + 1 < height ? 1 : 0, xc - static_cast<float>(x0), yc - static_cast<float>(y0)};
}

// The bilinear sample of one channel whose pixel (x0, y0) is at `at`, with neighbours `dx` to the
// right and `dy` below (0 at the border).
inline float bilinear(const float* at, int64_t dx, int64_t dy, float wx, float wy) {
  const float top = at[0] * (1.0f - wx) + at[dx] * wx;
  const float bottom = at[dy] * (1.0f - wx) + at[dy + dx] * wx;
  return top * (1.0f - wy) + bottom * wy;
}

// Sum over the window [i - pad, i + pad] cut at [0, n), for a row of n values: `out` gets it.
inline void window_sum_row(const float* in, float* padded, float* out, int64_t n, int64_t pad) {
  std::fill(padded, padded + pad, 0.0f);
  std::copy(in, in + n, padded + pad);
  std::fill(padded + pad + n, padded + 2 * pad + n, 0.0f);
  std::copy(padded, padded + n, out);
  for (int64_t k = 1; k <= 2 * pad; ++k) {
    const float* src = padded + k;
    for (int64_t i = 0; i < n; ++i) out[i] += src[i];
  }
}

at::Tensor search_along_rigid(const at::Tensor& image_in, const at::Tensor& other_in, const at::Tensor& rigid_in,
                              const at::Tensor& factors_in, const at::Tensor& proposal_in, const at::Tensor& bonus_in,
                              int64_t window, double outside_cost) {
  TORCH_CHECK(image_in.dim() == 4 && other_in.sizes() == image_in.sizes(), "search_along_rigid: expected image and other [B, C, H, W]");
  TORCH_CHECK(rigid_in.dim() == 4 && rigid_in.size(3) == 2, "search_along_rigid: expected rigid [B, H, W, 2]");
  TORCH_CHECK(window >= 1 && window % 2 == 1, "search_along_rigid: expected an odd window");
  const at::Tensor image = image_in.to(at::kFloat).contiguous();
  const at::Tensor other = other_in.to(at::kFloat).contiguous();
  const at::Tensor rigid = rigid_in.to(at::kFloat).contiguous();
  const at::Tensor factors = factors_in.to(at::kFloat).contiguous();
  const bool has_proposal = proposal_in.numel() > 0;
  const at::Tensor proposal = has_proposal ? proposal_in.to(at::kFloat).contiguous() : rigid;
  const int64_t batch = image.size(0), channels = image.size(1), height = image.size(2), width = image.size(3);
  const int64_t num_scales = factors.numel(), count = num_scales + (has_proposal ? 1 : 0);
  TORCH_CHECK(bonus_in.numel() == count, "search_along_rigid: expected one bonus per hypothesis");
  const at::Tensor bonus = bonus_in.to(at::kFloat).contiguous();
  const int64_t pixels = height * width, pad = window / 2;
  at::Tensor best = at::empty({batch, height, width}, image.options().dtype(at::kLong));
  const float* img = image.data_ptr<float>();
  const float* oth = other.data_ptr<float>();
  const float* rig = rigid.data_ptr<float>();
  const float* pro = proposal.data_ptr<float>();
  const float* fac = factors.data_ptr<float>();
  const float* bon = bonus.data_ptr<float>();
  int64_t* out = best.data_ptr<int64_t>();
  const float outside = static_cast<float>(outside_cost);
  const float inv_channels = 1.0f / static_cast<float>(channels);
  // 1 / (how many window positions fall inside the image) per row and per column
  std::vector<float> row_weight(height), col_weight(width);
  for (int64_t i = 0; i < height; ++i)
    row_weight[i] = static_cast<float>(std::min(i + pad, height - 1) - std::max(i - pad, int64_t{0}) + 1);
  for (int64_t i = 0; i < width; ++i)
    col_weight[i] = static_cast<float>(std::min(i + pad, width - 1) - std::max(i - pad, int64_t{0}) + 1);

  at::parallel_for(0, batch, 1, [&](int64_t begin, int64_t end) {
    std::vector<float> cost(pixels), rows(pixels), box(width), padded(std::max(width, height) + 2 * pad);
    std::vector<float> best_cost(pixels);
    for (int64_t b = begin; b < end; ++b) {
      const float* own = img + b * channels * pixels;
      const float* src = oth + b * channels * pixels;
      const float* flow_r = rig + b * pixels * 2;
      const float* flow_p = pro + b * pixels * 2;
      int64_t* choice = out + b * pixels;
      std::fill(best_cost.begin(), best_cost.end(), std::numeric_limits<float>::infinity());
      std::fill(choice, choice + pixels, int64_t{0});
      for (int64_t h = 0; h < count; ++h) {
        const bool scaled = h < num_scales;
        const float factor = scaled ? fac[h] : 1.0f;
        const float* flow = scaled ? flow_r : flow_p;
        for (int64_t row = 0; row < height; ++row) {
          const float* __restrict__ f = flow + 2 * row * width;
          float* __restrict__ line = cost.data() + row * width;
          for (int64_t col = 0; col < width; ++col) {
            const float x = static_cast<float>(col) + factor * f[2 * col];
            const float y = static_cast<float>(row) + factor * f[2 * col + 1];
            if (!inside_image(x, y, height, width)) {
              line[col] = outside;
              continue;
            }
            const BilinearTap tap = bilinear_tap(x, y, height, width);
            const int64_t at = tap.y0 * width + tap.x0, i = row * width + col;
            float total;
            if (channels == 1) {  // luma, what inference passes: without the channel loop (the same sum)
              total = std::abs(bilinear(src + at, tap.right, tap.below * width, tap.wx, tap.wy) - own[i]);
            } else {
              total = 0.0f;
              for (int64_t c = 0; c < channels; ++c) {
                const float sample = bilinear(src + c * pixels + at, tap.right, tap.below * width, tap.wx, tap.wy);
                total += std::abs(sample - own[c * pixels + i]);
              }
            }
            line[col] = total * inv_channels;
          }
        }
        for (int64_t row = 0; row < height; ++row)
          window_sum_row(cost.data() + row * width, padded.data(), rows.data() + row * width, width, pad);
        const float bonus_h = bon[h];
        for (int64_t row = 0; row < height; ++row) {
          std::fill(box.begin(), box.end(), 0.0f);
          const int64_t first = std::max(row - pad, int64_t{0}), last = std::min(row + pad, height - 1);
          for (int64_t r = first; r <= last; ++r) {
            const float* line = rows.data() + r * width;
            for (int64_t col = 0; col < width; ++col) box[col] += line[col];
          }
          float* low = best_cost.data() + row * width;
          int64_t* pick = choice + row * width;
          for (int64_t col = 0; col < width; ++col) {
            const float value = box[col] / (row_weight[row] * col_weight[col]) - bonus_h;
            if (value < low[col]) {
              low[col] = value;
              pick[col] = h;
            }
          }
        }
      }
    }
  });
  return best;
}

at::Tensor local_cost_volume(const at::Tensor& target_in, const at::Tensor& source_in, int64_t radius) {
  TORCH_CHECK(target_in.dim() == 4 && source_in.sizes() == target_in.sizes(), "local_cost_volume: expected target and source [B, C, H, W]");
  TORCH_CHECK(radius >= 0, "local_cost_volume: expected radius >= 0");
  const at::Tensor target = target_in.to(at::kFloat).contiguous();
  const at::Tensor source = source_in.to(at::kFloat).contiguous();
  const int64_t batch = target.size(0), channels = target.size(1), height = target.size(2), width = target.size(3);
  const int64_t side = 2 * radius + 1, shifts = side * side, pixels = height * width;
  at::Tensor out = at::zeros({batch, shifts, height, width}, target.options());
  const float* t = target.data_ptr<float>();
  const float* s = source.data_ptr<float>();
  float* o = out.data_ptr<float>();
  const float inv_channels = 1.0f / static_cast<float>(channels);
  at::parallel_for(0, batch * shifts, 1, [&](int64_t begin, int64_t end) {
    for (int64_t job = begin; job < end; ++job) {
      const int64_t b = job / shifts, shift = job % shifts;
      const int64_t dy = shift / side - radius, dx = shift % side - radius;
      const int64_t row0 = std::max(int64_t{0}, -dy), row1 = std::min(height, height - dy);
      const int64_t col0 = std::max(int64_t{0}, -dx), col1 = std::min(width, width - dx);
      float* dst = o + job * pixels;
      for (int64_t c = 0; c < channels; ++c) {
        const float* tc = t + (b * channels + c) * pixels;
        const float* sc = s + (b * channels + c) * pixels;
        for (int64_t row = row0; row < row1; ++row) {
          const float* tr = tc + row * width;
          const float* sr = sc + (row + dy) * width + dx;
          float* dr = dst + row * width;
          for (int64_t col = col0; col < col1; ++col) dr[col] += tr[col] * sr[col];
        }
      }
      for (int64_t i = 0; i < pixels; ++i) dst[i] *= inv_channels;
    }
  });
  return out;
}

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
        if (!inside_image(u, w, height, width)) continue;
        const BilinearTap tap = bilinear_tap(u, w, height, width);
        const float* s = back + 2 * (tap.y0 * width + tap.x0);  // two channels, interleaved
        const float bq[2] = {bilinear(s, 2 * tap.right, 2 * width * tap.below, tap.wx, tap.wy),
                             bilinear(s + 1, 2 * tap.right, 2 * width * tap.below, tap.wx, tap.wy)};
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

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor> epipolar_parallax(const at::Tensor& flow_in,
                                                                             const at::Tensor& intrinsics_in,
                                                                             const at::Tensor& inverse_in,
                                                                             const at::Tensor& relative_in, double near_z) {
  TORCH_CHECK(flow_in.dim() == 4 && flow_in.size(3) == 2, "epipolar_parallax: expected flow [V, H, W, 2]");
  const int64_t views = flow_in.size(0), height = flow_in.size(1), width = flow_in.size(2);
  TORCH_CHECK(intrinsics_in.dim() == 3 && intrinsics_in.size(0) == views && inverse_in.sizes() == intrinsics_in.sizes(),
              "epipolar_parallax: expected intrinsics and their inverses [V, 3, 3]");
  TORCH_CHECK(relative_in.dim() == 3 && relative_in.size(0) == views && relative_in.size(1) == 4 && relative_in.size(2) == 4,
              "epipolar_parallax: expected transforms [V, 4, 4]");
  const at::Tensor flow = flow_in.to(at::kFloat).contiguous();
  const at::Tensor intrinsics = intrinsics_in.to(at::kFloat).contiguous();
  const at::Tensor inverse = inverse_in.to(at::kFloat).contiguous();
  const at::Tensor relative = relative_in.to(at::kFloat).contiguous();
  const auto options = flow.options();
  at::Tensor depth = at::empty({views, height, width}, options);
  at::Tensor off_line = at::empty({views, height, width}, options);
  at::Tensor parallax = at::empty({views, height, width, 2}, options);
  at::Tensor valid = at::empty({views, height, width}, options.dtype(at::kBool));
  const float* fl = flow.data_ptr<float>();
  const float* kk = intrinsics.data_ptr<float>();
  const float* ki = inverse.data_ptr<float>();
  const float* rel = relative.data_ptr<float>();
  float* zo = depth.data_ptr<float>();
  float* lo = off_line.data_ptr<float>();
  float* po = parallax.data_ptr<float>();
  bool* vo = valid.data_ptr<bool>();
  const float nz = static_cast<float>(near_z);
  const float max_u = static_cast<float>(width - 1), max_v = static_cast<float>(height - 1);

  at::parallel_for(0, views * height, 16, [&](int64_t begin, int64_t end) {
    for (int64_t vr = begin; vr < end; ++vr) {
      const int64_t v = vr / height, row = vr % height;
      const float* k = kk + 9 * v;
      const float* m = ki + 9 * v;
      const float* r = rel + 16 * v;
      const float t[3] = {r[3], r[7], r[11]};
      const float y = static_cast<float>(row);
      for (int64_t col = 0; col < width; ++col) {
        const int64_t i = vr * width + col;
        const float x = static_cast<float>(col);
        float ray[3], a[3], e[3];
        for (int j = 0; j < 3; ++j) ray[j] = m[3 * j] * x + m[3 * j + 1] * y + m[3 * j + 2];
        for (int j = 0; j < 3; ++j) a[j] = r[4 * j] * ray[0] + r[4 * j + 1] * ray[1] + r[4 * j + 2] * ray[2];
        const float tu = x + fl[2 * i], tv = y + fl[2 * i + 1];
        for (int j = 0; j < 3; ++j) e[j] = m[3 * j] * tu + m[3 * j + 1] * tv + m[3 * j + 2];
        // z (a_xy - e_xy a_z) = e_xy t_z - t_xy, least squares over both axes
        const float c0 = a[0] - e[0] * a[2], c1 = a[1] - e[1] * a[2];
        const float r0 = e[0] * t[2] - t[0], r1 = e[1] * t[2] - t[1];
        const float z = (c0 * r0 + c1 * r1) / std::max(c0 * c0 + c1 * c1, 1e-12f);
        const float p[3] = {z * a[0] + t[0], z * a[1] + t[1], z * a[2] + t[2]};
        float proj[3], inf[3];
        for (int j = 0; j < 3; ++j) proj[j] = k[3 * j] * p[0] + k[3 * j + 1] * p[1] + k[3 * j + 2] * p[2];
        for (int j = 0; j < 3; ++j) inf[j] = k[3 * j] * a[0] + k[3 * j + 1] * a[1] + k[3 * j + 2] * a[2];
        const float pz = std::max(proj[2], 1e-6f), iz = std::max(inf[2], 1e-6f);
        const float pu = proj[0] / pz, pv = proj[1] / pz, iu = inf[0] / iz, iv = inf[1] / iz;
        zo[i] = z;
        lo[i] = std::sqrt((pu - tu) * (pu - tu) + (pv - tv) * (pv - tv));
        po[2 * i] = pu - iu;
        po[2 * i + 1] = pv - iv;
        const bool inside = tu >= 0.0f && tu <= max_u && tv >= 0.0f && tv <= max_v;
        vo[i] = p[2] > nz && a[2] > 0.0f && inside && std::isfinite(z);
      }
    }
  });
  return {depth, off_line, parallax, valid};
}

std::tuple<at::Tensor, at::Tensor> rigid_flow_dense(const at::Tensor& depth_in, const at::Tensor& intrinsics_in,
                                                    const at::Tensor& src_to_dst_in, const at::Tensor& dst_intrinsics_in) {
  TORCH_CHECK(depth_in.dim() == 3, "rigid_flow_dense: expected depth [B, H, W]");
  const int64_t views = depth_in.size(0), height = depth_in.size(1), width = depth_in.size(2);
  TORCH_CHECK(intrinsics_in.dim() == 3 && intrinsics_in.size(0) == views && dst_intrinsics_in.sizes() == intrinsics_in.sizes(),
              "rigid_flow_dense: expected intrinsics [B, 3, 3]");
  TORCH_CHECK(src_to_dst_in.dim() == 3 && src_to_dst_in.size(0) == views && src_to_dst_in.size(1) == 4 &&
                  src_to_dst_in.size(2) == 4,
              "rigid_flow_dense: expected transforms [B, 4, 4]");
  const at::Tensor depth = depth_in.to(at::kFloat).contiguous();
  const at::Tensor intrinsics = intrinsics_in.to(at::kFloat).contiguous();
  const at::Tensor dst_intrinsics = dst_intrinsics_in.to(at::kFloat).contiguous();
  const at::Tensor transform = src_to_dst_in.to(at::kFloat).contiguous();
  at::Tensor flow = at::empty({views, height, width, 2}, depth.options());
  at::Tensor z_out = at::empty({views, height, width}, depth.options());
  const float* d = depth.data_ptr<float>();
  const float* ks = intrinsics.data_ptr<float>();
  const float* kd = dst_intrinsics.data_ptr<float>();
  const float* tr = transform.data_ptr<float>();
  float* fo = flow.data_ptr<float>();
  float* zo = z_out.data_ptr<float>();
  at::parallel_for(0, views * height, 16, [&](int64_t begin, int64_t end) {
    for (int64_t vr = begin; vr < end; ++vr) {
      const int64_t v = vr / height, row = vr % height;
      const float* k = ks + 9 * v;
      const float* kt = kd + 9 * v;
      const float* m = tr + 16 * v;
      const float fy = k[4], cy = k[5], fx = k[0], cx = k[2], skew = k[1];
      const float vv = static_cast<float>(row);
      const float y = (vv - cy) / fy;
      for (int64_t col = 0; col < width; ++col) {
        const int64_t i = vr * width + col;
        const float uu = static_cast<float>(col);
        const float x = (uu - cx - skew * y) / fx;
        const float depth_i = d[i];
        const float p0 = x * depth_i, p1 = y * depth_i, p2 = depth_i;
        float q[3];
        for (int r = 0; r < 3; ++r) {
          float acc = m[4 * r + 3] + p0 * m[4 * r];
          acc = acc + p1 * m[4 * r + 1];
          acc = acc + p2 * m[4 * r + 2];
          q[r] = acc;
        }
        const float zc = std::max(q[2], 1e-6f);
        const float xn = q[0] / zc, yn = q[1] / zc;
        const float u = kt[0] * xn + kt[1] * yn + kt[2];
        const float w = kt[4] * yn + kt[5];
        fo[2 * i] = u - uu;
        fo[2 * i + 1] = w - vv;
        zo[i] = q[2];
      }
    }
  });
  return {flow, z_out};
}

at::Tensor fb_consistent(const at::Tensor& flow_in, const at::Tensor& flow_back_in, double alpha, double beta) {
  TORCH_CHECK(flow_in.dim() == 4 && flow_in.size(3) == 2 && flow_back_in.sizes() == flow_in.sizes(),
              "fb_consistent: expected both flows [B, H, W, 2]");
  const int64_t views = flow_in.size(0), height = flow_in.size(1), width = flow_in.size(2);
  const at::Tensor flow = flow_in.to(at::kFloat).contiguous();
  const at::Tensor flow_back = flow_back_in.to(at::kFloat).contiguous();
  at::Tensor out = at::empty({views, height, width}, flow.options().dtype(at::kBool));
  const float* fw = flow.data_ptr<float>();
  const float* bw = flow_back.data_ptr<float>();
  bool* ok = out.data_ptr<bool>();
  const int64_t pixels = height * width;
  const float a = static_cast<float>(alpha), b = static_cast<float>(beta);
  at::parallel_for(0, views * height, 16, [&](int64_t begin, int64_t end) {
    for (int64_t vr = begin; vr < end; ++vr) {
      const int64_t v = vr / height, row = vr % height;
      const float* back = bw + v * pixels * 2;
      for (int64_t col = 0; col < width; ++col) {
        const int64_t i = vr * width + col;
        const float f0 = fw[2 * i], f1 = fw[2 * i + 1];
        const float u = static_cast<float>(col) + f0, w = static_cast<float>(row) + f1;
        if (!inside_image(u, w, height, width)) {
          ok[i] = false;
          continue;
        }
        const BilinearTap tap = bilinear_tap(u, w, height, width);
        const float* s = back + 2 * (tap.y0 * width + tap.x0);
        const float bq[2] = {bilinear(s, 2 * tap.right, 2 * width * tap.below, tap.wx, tap.wy),
                             bilinear(s + 1, 2 * tap.right, 2 * width * tap.below, tap.wx, tap.wy)};
        const float e0 = f0 + bq[0], e1 = f1 + bq[1];
        ok[i] = e0 * e0 + e1 * e1 < a * ((f0 * f0 + f1 * f1) + (bq[0] * bq[0] + bq[1] * bq[1])) + b;
      }
    }
  });
  return out;
}

std::tuple<at::Tensor, at::Tensor> rig_stereo(const at::Tensor& end_in, const at::Tensor& back_in, const at::Tensor& world_a_in,
                                              const at::Tensor& world_b_in, const at::Tensor& geometry_in, int64_t x0, int64_t y0,
                                              int64_t back_x0, int64_t back_y0, double consistency_px, double epipolar_px,
                                              double min_parallax, double z_near, double z_far, double near_z) {
  TORCH_CHECK(end_in.dim() == 3 && end_in.size(2) == 2, "rig_stereo: expected end [h, w, 2]");
  TORCH_CHECK(back_in.dim() == 3 && back_in.size(2) == 2, "rig_stereo: expected back [hb, wb, 2]");
  TORCH_CHECK(world_a_in.dim() == 2 && world_a_in.size(0) == end_in.size(0) && world_a_in.size(1) == end_in.size(1),
              "rig_stereo: expected world_a [h, w] like end");
  TORCH_CHECK(world_b_in.dim() == 2, "rig_stereo: expected world_b [H, W]");
  TORCH_CHECK(geometry_in.numel() == 30, "rig_stereo: expected geometry of 30 values (M, t, K_b, K_b^-1)");
  const at::Tensor end = end_in.to(at::kFloat).contiguous(), back = back_in.to(at::kFloat).contiguous();
  const at::Tensor world_a = world_a_in.to(at::kBool).contiguous(), world_b = world_b_in.to(at::kBool).contiguous();
  const at::Tensor geometry = geometry_in.to(at::kFloat).contiguous();
  const int64_t h = end.size(0), w = end.size(1), hb = back.size(0), wb = back.size(1);
  const int64_t height = world_b.size(0), width = world_b.size(1);
  at::Tensor z_out = at::zeros({h, w}, end.options()), parallax_out = at::zeros({h, w}, end.options());
  const float* e = end.data_ptr<float>();
  const float* bk = back.data_ptr<float>();
  const bool* wa = world_a.data_ptr<bool>();
  const bool* wbp = world_b.data_ptr<bool>();
  const float* g = geometry.data_ptr<float>();
  const float* m = g;        // M = R K_a^-1, row-major
  const float* t = g + 9;    // translation a -> b
  const float* k = g + 12;   // K_b
  const float* ki = g + 21;  // K_b^-1
  float* zo = z_out.data_ptr<float>();
  float* po = parallax_out.data_ptr<float>();
  const float consistency2 = static_cast<float>(consistency_px * consistency_px);
  const float max_off = static_cast<float>(epipolar_px), least = static_cast<float>(min_parallax);
  const float lo = static_cast<float>(z_near), hi = static_cast<float>(z_far), nz = static_cast<float>(near_z);
  at::parallel_for(0, h, 8, [&](int64_t begin, int64_t stop) {
    for (int64_t i = begin; i < stop; ++i) {
      for (int64_t j = 0; j < w; ++j) {
        const int64_t idx = i * w + j;
        if (!wa[idx]) continue;
        const float px = static_cast<float>(x0 + j), py = static_cast<float>(y0 + i);
        const float qx = e[2 * idx], qy = e[2 * idx + 1];
        if (!std::isfinite(qx) || !std::isfinite(qy)) continue;
        const float rx = std::nearbyint(qx), ry = std::nearbyint(qy);
        // on one of b's world pixels
        if (!(rx >= 0.0f && rx < static_cast<float>(width) && ry >= 0.0f && ry < static_cast<float>(height))) continue;
        if (!wbp[static_cast<int64_t>(ry) * width + static_cast<int64_t>(rx)]) continue;
        // b's match back lands near p
        const float cx = rx - static_cast<float>(back_x0), cy = ry - static_cast<float>(back_y0);
        if (!(cx >= 0.0f && cx < static_cast<float>(wb) && cy >= 0.0f && cy < static_cast<float>(hb))) continue;
        const float* r = bk + 2 * (static_cast<int64_t>(cy) * wb + static_cast<int64_t>(cx));
        const float dx = r[0] - px, dy = r[1] - py;
        if (!(dx * dx + dy * dy <= consistency2)) continue;
        // triangulation
        const float a0 = m[0] * px + m[1] * py + m[2], a1 = m[3] * px + m[4] * py + m[5], a2 = m[6] * px + m[7] * py + m[8];
        const float xn = ki[0] * qx + ki[1] * qy + ki[2], yn = ki[4] * qy + ki[3] * qx + ki[5];
        const float c0 = a0 - xn * a2, c1 = a1 - yn * a2;
        const float r0 = xn * t[2] - t[0], r1 = yn * t[2] - t[1];
        const float z = (c0 * r0 + c1 * r1) / std::max(c0 * c0 + c1 * c1, 1e-12f);
        const float p0 = z * a0 + t[0], p1 = z * a1 + t[1], p2 = z * a2 + t[2];
        if (!(std::isfinite(z) && p2 > nz && a2 > 0.0f)) continue;
        const float pz = std::max(k[6] * p0 + k[7] * p1 + k[8] * p2, 1e-6f);
        const float pu = (k[0] * p0 + k[1] * p1 + k[2] * p2) / pz, pv = (k[3] * p0 + k[4] * p1 + k[5] * p2) / pz;
        const float iz = std::max(k[6] * a0 + k[7] * a1 + k[8] * a2, 1e-6f);
        const float iu = (k[0] * a0 + k[1] * a1 + k[2] * a2) / iz, iv = (k[3] * a0 + k[4] * a1 + k[5] * a2) / iz;
        const float off = std::hypot(pu - qx, pv - qy), parallax = std::hypot(pu - iu, pv - iv);
        if (off <= max_off && parallax >= least && z >= lo && z <= hi) {
          zo[idx] = z;
          po[idx] = parallax;
        }
      }
    }
  });
  return {z_out, parallax_out};
}

}  // namespace

TORCH_LIBRARY_FRAGMENT(drivingscene_render, m) {
  m.def("search_along_rigid(Tensor image, Tensor other, Tensor rigid, Tensor factors, Tensor proposal, Tensor bonus, "
        "int window, float outside_cost) -> Tensor",
        &search_along_rigid);
  m.def("local_cost_volume(Tensor target, Tensor source, int radius) -> Tensor", &local_cost_volume);
  m.def("lift_dense(Tensor depth_src, Tensor depth_dst, Tensor flow, Tensor flow_back, Tensor candidate, Tensor intrinsics, "
        "Tensor src_to_world, Tensor dst_to_world, float alpha, float beta) -> (Tensor, Tensor)",
        &lift_dense);
  m.def("epipolar_parallax(Tensor flow, Tensor intrinsics, Tensor inverse, Tensor relative, float near_z) "
        "-> (Tensor, Tensor, Tensor, Tensor)",
        &epipolar_parallax);
  m.def("rigid_flow_dense(Tensor depth, Tensor intrinsics, Tensor src_to_dst, Tensor dst_intrinsics) -> (Tensor, Tensor)",
        &rigid_flow_dense);
  m.def("fb_consistent(Tensor flow, Tensor flow_back, float alpha, float beta) -> Tensor", &fb_consistent);
  m.def("rig_stereo(Tensor end, Tensor back, Tensor world_a, Tensor world_b, Tensor geometry, int x0, int y0, int back_x0, "
        "int back_y0, float consistency_px, float epipolar_px, float min_parallax, float z_near, float z_far, float near_z) "
        "-> (Tensor, Tensor)",
        &rig_stereo);
}
