// The photometric search along the rigid flow (the optional compiled path of
// drivingscene.geometry.flow_search.search_along_rigid), and the local cost volume of the
// residual flow network at inference (drivingscene.models.residual_flow.local_cost_volume).
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
#include <ATen/ATen.h>
#include <ATen/Parallel.h>
#include <torch/library.h>

#include <algorithm>
#include <cmath>
#include <limits>
#include <vector>

namespace {

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
        const float x_max = static_cast<float>(width - 1), y_max = static_cast<float>(height - 1);
        const int x0_max = static_cast<int>(std::max(width - 2, int64_t{0}));
        const int y0_max = static_cast<int>(std::max(height - 2, int64_t{0}));
        const int w = static_cast<int>(width);
        for (int64_t row = 0; row < height; ++row) {
          const float* __restrict__ f = flow + 2 * row * width;
          float* __restrict__ line = cost.data() + row * width;
          for (int64_t col = 0; col < width; ++col) {
            const float x = static_cast<float>(col) + factor * f[2 * col];
            const float y = static_cast<float>(row) + factor * f[2 * col + 1];
            if (!(x >= -0.5f && x <= width - 0.5f && y >= -0.5f && y <= height - 0.5f)) {
              line[col] = outside;
              continue;
            }
            const float xc = std::min(std::max(x, 0.0f), x_max);
            const float yc = std::min(std::max(y, 0.0f), y_max);
            const int x0 = std::min(static_cast<int>(xc), x0_max);  // xc >= 0: truncation is floor
            const int y0 = std::min(static_cast<int>(yc), y0_max);
            const int dx = x0 + 1 < w ? 1 : 0, dy = y0 + 1 < static_cast<int>(height) ? w : 0;
            const float wx = xc - static_cast<float>(x0), wy = yc - static_cast<float>(y0);
            const int at = y0 * w + x0;
            const int64_t i = row * width + col;
            float total = 0.0f;
            for (int64_t c = 0; c < channels; ++c) {
              const float* s = src + c * pixels + at;
              const float top = s[0] * (1.0f - wx) + s[dx] * wx;
              const float bottom = s[dy] * (1.0f - wx) + s[dy + dx] * wx;
              total += std::abs(top * (1.0f - wy) + bottom * wy - own[c * pixels + i]);
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

}  // namespace

TORCH_LIBRARY_FRAGMENT(drivingscene_render, m) {
  m.def("search_along_rigid(Tensor image, Tensor other, Tensor rigid, Tensor factors, Tensor proposal, Tensor bonus, "
        "int window, float outside_cost) -> Tensor",
        &search_along_rigid);
  m.def("local_cost_volume(Tensor target, Tensor source, int radius) -> Tensor", &local_cost_volume);
}
