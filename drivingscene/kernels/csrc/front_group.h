// Surface averaging's front group (composite.cpp's module comment), shared by the compositing
// kernels and the colour solve (color_solve.cpp).
#pragma once

#include <cstdint>

namespace drivingscene_front {

// Whether a splat at depth z joins the front group holding `count` splats (its limit z_limit).
inline bool joins_front(int64_t count, float tol, float z, float z_limit) { return count == 0 || (tol > 0.0f && z <= z_limit); }

// The front group's coverage A = 1 - P and the factor A / S_F of its splats' alphas; one splat:
// exactly plain compositing's w = alpha (no 1 - (1 - alpha) rounding); none: zero.
struct FrontWeights {
  float cover, scale;
};
inline FrontWeights front_weights(int64_t count, float alpha_sum, float trans) {
  if (count == 1) return {alpha_sum, 1.0f};
  const float cover = 1.0f - trans;
  return {cover, alpha_sum > 0.0f ? cover / alpha_sum : 0.0f};
}

}  // namespace drivingscene_front
