// The pair finder's band scatter (find_pairs.cpp), shared with the colour solve (color_solve.cpp).
#pragma once

#include <ATen/ATen.h>

#include <cstdint>
#include <vector>

namespace drivingscene_pairs {

constexpr int kBandRows = 8;

struct Bins {
  std::vector<int64_t> offsets;  // [tasks + 1]
  std::vector<int32_t> ids;      // splat ids, depth order within each task
};

struct SplatArrays {
  const float* means2d;
  const float* conics;
  const float* opacities;
  const float* sigma_max;
  const int32_t* boxes;
};

// The inputs checked, and the splats binned by task (camera, band of kBandRows rows).
struct Prepared {
  int64_t num_cams, bands;
  Bins bins;
  SplatArrays s;
};

Prepared prepare(const at::Tensor& means2d, const at::Tensor& conics, const at::Tensor& opacities, const at::Tensor& sigma_max,
                 const at::Tensor& boxes, const at::Tensor& camera_offsets, int64_t width, int64_t height, int64_t max_layers);

// Scatter the band's splats, front to back, into its rows [row0, row1): `out_band` holds the
// band's pixels' lists (max_layers each, row-major from row0), `counts` (if given) their lengths.
// Where `alpha_band` is given, each listed pair's alpha is written beside its id. `exact_exp`:
// alpha from a float64 exp rounded to float32, as the torch path (the rasterizer, whose two paths
// must choose the same pairs); false: a float32 exp, a quarter less time for the colour solve,
// whose pairs may then differ from the torch path's where a transmittance lands on the cut.
void scatter_band(const SplatArrays& s, const int32_t* ids, int64_t count, int row0, int row1, int width, int max_layers,
                  int32_t* out_band, float* alpha_band, int32_t* counts, bool exact_exp = true);

}  // namespace drivingscene_pairs
