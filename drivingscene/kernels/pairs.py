"""The rasterizer's pair finding (``csrc/find_pairs.cpp``)."""

from __future__ import annotations

from torch import Tensor

from drivingscene.kernels.build import call, compiled


@compiled
def find_pairs(
    means2d: Tensor,  # [M, 2] float32 pixel centres of the splats (visible camera-Gaussian pairs)
    conics: Tensor,  # [M, 3] float32 inverse 2D covariances (a, b, c)
    opacities: Tensor,  # [M] float32
    sigma_max: Tensor,  # [M] float32 cut: a splat contributes where sigma <= sigma_max
    boxes: Tensor,  # [M, 4] int32 pixel boxes x0, x1, y0, y1 (inclusive, clipped)
    camera_offsets: Tensor,  # [B + 1] int64: splats of camera b are camera_offsets[b]:camera_offsets[b + 1]
    width: int,
    height: int,
    max_layers: int,
) -> Tensor:
    """Each pixel's contributing splats, front to back: ``[B * H * W, max_layers]`` int32 splat
    ids (pixels row-major per camera), -1 where empty.

    Per pixel, the first ``max_layers`` splats (in the given depth order) that pass the cut,
    with front-to-back transmittance and the 3DGS early stop (a splat that would bring the
    transmittance below 1e-4 is dropped and the pixel stops). Every input must be a contiguous
    CPU tensor of the dtype above. Reference path: ``drivingscene.render.composite.find_pairs_torch``
    (the same float32 operations in the same order: identical ids)."""
    return call("find_pairs", means2d, conics, opacities, sigma_max, boxes, camera_offsets, width, height, max_layers)


@compiled
def splat_boxes(
    means2d: Tensor,  # [M, 2] float32
    conics: Tensor,  # [M, 3] float32
    sigma_max: Tensor,  # [M] float32 the cut
    radii: Tensor,  # [M] float32 (0: not drawn)
    width: int,
    height: int,
) -> Tensor:
    """Each splat's pixel box ``[M, 4]`` int32 x0, x1, y0, y1 (inclusive, clipped; empty where
    x0 > x1): the ellipse ``sigma <= sigma_max`` with a small margin. Reference path:
    ``drivingscene.render.composite.splat_boxes_torch`` (the same float64 operations: the same
    boxes)."""
    return call("splat_boxes", means2d, conics, sigma_max, radii, width, height)
