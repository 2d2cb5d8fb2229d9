"""Per-pixel surfel frames of the Gaussian assembly and the Gaussian head's activation (``csrc/surfels.cpp``)."""

from __future__ import annotations

from torch import Tensor

from drivingscene.kernels.build import call, compiled


@compiled
def surfel_frames(
    depth: Tensor,  # [V, H, W] z-depth, metres (no gradient)
    intrinsics: Tensor,  # [V, 3, 3]
    footprint: float,  # splat diameter on the image, pixels
    thickness: float,  # along the normal, relative to the footprint
    min_cos: float,  # cap of the stretch along the slant: at most 1 / min_cos
) -> tuple[Tensor, Tensor]:
    """Default camera-axis rotations ``[V, H, W, 4]`` (w, x, y, z) and log scales ``[V, H, W, 3]``
    of one surfel per pixel (the EWA footprint on the surface), float32, in one pass per row.

    CPU tensors, any float dtype (computed in float32); not differentiable. Reference path:
    ``drivingscene.gaussians.assembly.surfel_frames_torch`` (the same Gaussians up to float rounding)."""
    return call("surfel_frames", depth, intrinsics, footprint, thickness, min_cos)


@compiled
def activate_surfels(
    depth: Tensor,  # [B, H, W] z-depth, metres (no gradient)
    intrinsics: Tensor,  # [B, 3, 3]
    raw: Tensor,  # [B, H, W, 8 + 3K] the head's raw outputs
    images: Tensor,  # [B, 3, H, W] in [0, 1]
    footprint: float,
    thickness: float,
    min_cos: float,
    opacity_bias: float,  # added to the raw opacity logit
    sh_c0: float,  # the degree-0 SH constant
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The Gaussian head's activation at inference, fused with the `surfel_frames` it modifies:
    log scales ``[B, H, W, 3]``, quaternions ``[B, H, W, 4]`` (w, x, y, z), opacity logits
    ``[B, H, W]`` and SH coefficients ``[B, H, W, K, 3]``, float32.

    CPU tensors, any float dtype (computed in float32); no gradients. Reference path:
    ``drivingscene.models.gaussian_head.GaussianHead._activate`` (the same up to float rounding)."""
    return call("activate_surfels", depth, intrinsics, raw, images, footprint, thickness, min_cos, opacity_bias, sh_c0)


@compiled
def extend_along_rays(
    points: Tensor,  # [N, 3] means in their source camera's axes, metres
    quats: Tensor,  # [N, 4] w, x, y, z, the same axes
    log_scales: Tensor,  # [N, 3]
    sigma: Tensor,  # [N] metres added along the view ray (<= 0: unchanged)
) -> tuple[Tensor, Tensor]:
    """Quaternions ``[N, 4]`` and log scales ``[N, 3]`` of the Gaussians whose covariance gained
    ``sigma^2`` along the unit ray from the camera centre to the mean, float32 (a closed-form
    eigen-decomposition per Gaussian, in double precision).

    CPU tensors, any float dtype; not differentiable. Reference path:
    ``drivingscene.gaussians.assembly.extend_along_rays_torch`` (the same covariances up to float rounding)."""
    return call("extend_along_rays", points, quats, log_scales, sigma)


@compiled
def pixel_footprints(
    depth: Tensor,  # [V, H, W] z-depth, metres (no gradient)
    intrinsics: Tensor,  # [V, 3, 3]
    quats: Tensor,  # [V, H, W, 4] w, x, y, z, camera axes
    log_scales: Tensor,  # [V, H, W, 3]
    max_footprint: float,  # pixels (sigma) of the source view; <= 0: no cap
    floor: float,  # pixels^2 of the source view; <= 0: no floor
) -> Tensor:
    """Log scales ``[V, H, W, 3]`` of per-pixel Gaussians with the footprint rule (shrunk to
    ``max_footprint`` in their own view, then widened by ``floor``), float32, one pass per row.

    CPU tensors, any float dtype (computed in float32); not differentiable. Reference path:
    ``drivingscene.gaussians.assembly.pixel_footprints`` with ``backend="torch"`` (the same log
    scales up to float rounding)."""
    return call("pixel_footprints", depth, intrinsics, quats, log_scales, max_footprint, floor)
