"""The colour solve over the images' own layers (``csrc/color_solve.cpp``)."""

from __future__ import annotations

from torch import Tensor

from drivingscene.kernels.build import call, compiled


@compiled
def own_layer_solve(
    means2d: Tensor,  # [M, 2] float32 the splats, as find_pairs takes them
    conics: Tensor,  # [M, 3] float32
    opacities: Tensor,  # [M] float32
    sigma_max: Tensor,  # [M] float32
    boxes: Tensor,  # [M, 4] int32
    camera_offsets: Tensor,  # [B + 1] int64 (splats in compositing order within each image)
    width: int,
    height: int,
    max_layers: int,
    depths: Tensor,  # [M] float32 the splats' z (surface averaging's front group)
    member_offsets: Tensor,  # [M + 1] int64: splat i stands for members[member_offsets[i]:member_offsets[i + 1]]
    members: Tensor,  # [K] int64 pixels (indices into the B * H * W pixels), each stood for by one splat at most
    target: Tensor,  # [B * H * W, C] float32 what each pixel should render
    start: Tensor,  # [M, C] float32 the splats' starting colours
    iterations: int,
    tolerance: float,  # surface averaging, as composite_forward
    max_color: float,  # colours are kept in [0, max_color]
    min_coverage: float,  # a splat's colour moves only where its pixel's accumulated alpha reaches this
) -> Tensor:
    """The colour solve of ``drivingscene.render.color_solve``: ``iterations`` Jacobi (Van Cittert)
    steps ``c_i <- clamp(c_i + mean over p in P_i of (target(p) - C(p) / A(p)), 0, max_color)``, with
    ``P_i`` splat i's pixels where ``A`` reaches ``min_coverage`` (c_i kept where none does), ``C``
    and ``A`` the colour and accumulated alpha that ``find_pairs`` + ``composite_forward`` give over a
    black background; the pairs are found and their weights formed once, each step is a sparse
    product. Returns the splats' colours ``[M, C]`` float32. CPU tensors. Reference path:
    ``solve_pixel_colors`` or ``solve_gaussian_colors`` with ``backend="torch"`` (a compositing pass per step; equal up to float
    rounding: the pairs' alphas here take the pair finder's float64 exponential)."""
    return call(
        "own_layer_solve",
        means2d,
        conics,
        opacities,
        sigma_max,
        boxes,
        camera_offsets,
        width,
        height,
        max_layers,
        depths,
        member_offsets,
        members,
        target,
        start,
        int(iterations),
        float(tolerance),
        float(max_color),
        float(min_coverage),
    )
