"""The rasterizer's compositing over its pair buffer, forward and backward (``csrc/composite.cpp``)."""

from __future__ import annotations

from torch import Tensor

from drivingscene.kernels.build import call, compiled


@compiled
def composite_forward(
    packed: Tensor,  # [M, 7 + C] float32 splat rows: mean x, mean y, conic a, b, c, opacity, z, C colours
    backgrounds: Tensor,  # [B, C] float32
    pair_ids: Tensor,  # [B * H * W, L] int32 splat ids per pixel, front to back, -1 where empty
    width: int,
    height: int,
    tolerance: float = 0.0,
) -> list[Tensor]:
    """Front-to-back compositing of each pixel's splats: colours ``[P, C]`` over the backgrounds,
    expected z-depth ``[P]`` (0 where the accumulated alpha is below 1e-6) and accumulated alpha
    ``[P]``, float32 (P = B * H * W, pixels row-major per camera). ``tolerance`` > 0 averages each
    pixel's front surface (the splats within that relative depth of its first) instead of
    compositing it (``drivingscene.render.composite``'s module docstring).

    CPU tensors (computed in float32); no autograd (``composite_backward`` is the backward).
    Reference path: ``drivingscene.render.composite.composite_torch`` (the
    same operations, sums in another order: equal up to float rounding)."""
    return call("composite_forward", packed, backgrounds, pair_ids, width, height, float(tolerance))


@compiled
def composite_backward(
    packed: Tensor,  # [M, 7 + C] as composite_forward
    backgrounds: Tensor,  # [B, C]
    pair_ids: Tensor,  # [B * H * W, L] int32
    width: int,
    height: int,
    depth: Tensor,  # [P] composite_forward's depth
    weight_sum: Tensor,  # [P] composite_forward's accumulated alpha
    grad_rgb: Tensor,  # [P, C] dL/dcolours
    grad_depth: Tensor,  # [P] dL/ddepth
    grad_alpha: Tensor,  # [P] dL/dalpha
    tolerance: float = 0.0,  # as composite_forward
) -> list[Tensor]:
    """The gradients of the loss with respect to ``packed`` ``[M, 7 + C]`` and ``backgrounds``
    ``[B, C]``, float32: per pixel the 3DGS backward (no gradient through alpha where it is
    clamped at 0.99), the rows' gradients summed over the pixels that use them.

    CPU tensors (computed in float32). Reference path:
    ``drivingscene.render.composite.composite_backward_torch`` (equal up to float rounding)."""
    return call(
        "composite_backward",
        packed,
        backgrounds,
        pair_ids,
        width,
        height,
        depth,
        weight_sum,
        grad_rgb,
        grad_depth,
        grad_alpha,
        float(tolerance),
    )
