"""Per-pixel Gaussians from depth: the assembly shared by the model and the oracle.

Every valid pixel of every view becomes one Gaussian at its back-projected surface point. Scales
and rotations are given in camera axes (the network predicts them per pixel) and turned into the
world frame with the camera's rotation; without them each Gaussian is a camera-facing disc about
one pixel footprint wide.
"""

from __future__ import annotations

import torch
from torch import Tensor

from drivingscene.gaussians.core import Gaussians, rgb_to_sh0
from drivingscene.geometry.camera import unproject
from drivingscene.geometry.se3 import matrix_to_quat, quat_multiply, transform_points

# Default footprint: sigma = FOOTPRINT * depth / focal in the image plane; thin along the viewing
# ray. With the renderer's 0.3 px^2 low-pass the splat of a pixel has sigma ~0.65 px, which still
# closes the surface (measured on the demo scene: 0.7 -> 24.6 dB in the input views, 0.35 -> 29.4 dB,
# and intermediate frames 22.0 -> 23.5 dB; see docs/gaussian-core.md).
FOOTPRINT = 0.35
THICKNESS = 0.1


def default_scales(depth: Tensor, intrinsics: Tensor) -> Tensor:
    """Camera-axis scales ``[V, H, W, 3]`` of one-pixel discs facing the camera."""
    focal = intrinsics[:, None, None, :2].diagonal(dim1=-2, dim2=-1)  # [V, 1, 1, 2]
    footprint = FOOTPRINT * depth[..., None] / focal
    thickness = THICKNESS * footprint.mean(-1, keepdim=True)
    return torch.cat([footprint, thickness], dim=-1)


def gaussians_from_pixels(
    depth: Tensor,  # [V, H, W] z-depth, metres
    intrinsics: Tensor,  # [V, 3, 3]
    cam_to_world: Tensor,  # [V, 4, 4]
    colors: Tensor,  # [V, H, W, 3] RGB in [0, 1], or [V, H, W, K, 3] SH coefficients
    *,
    keyframe: int,
    log_scales: Tensor | None = None,  # [V, H, W, 3] log metres, camera axes
    quats: Tensor | None = None,  # [V, H, W, 4] w, x, y, z, camera axes
    opacity_logits: Tensor | None = None,  # [V, H, W]
    flows: Tensor | None = None,  # [V, H, W, 3] world displacement to the other keyframe
    valid: Tensor | None = None,  # [V, H, W] bool; default depth > 0
    default_opacity: float = 0.95,
) -> Gaussians:
    """One Gaussian per valid pixel, in the world frame (differentiable in every input)."""
    num_views, height, width = depth.shape
    if valid is None:
        valid = depth > 0
    points_cam = unproject(depth, intrinsics)  # [V, H, W, 3]
    means = transform_points(cam_to_world, points_cam.flatten(1, 2)).view(num_views, height, width, 3)
    if log_scales is None:
        log_scales = torch.log(default_scales(depth, intrinsics))
    cam_quats = matrix_to_quat(cam_to_world[:, :3, :3])[:, None, None, :].expand(num_views, height, width, 4)
    world_quats = cam_quats if quats is None else quat_multiply(cam_quats, quats)
    sh = rgb_to_sh0(colors)[..., None, :] if colors.ndim == 4 else colors
    if opacity_logits is None:
        opacity_logits = torch.full_like(depth, torch.logit(torch.tensor(default_opacity)).item())
    cameras = torch.arange(num_views, device=depth.device)[:, None, None].expand(num_views, height, width)
    n = int(valid.sum())
    return Gaussians(
        means=means[valid],
        quats=world_quats[valid],
        log_scales=log_scales[valid],
        opacity_logits=opacity_logits[valid],
        sh=sh[valid],
        flows=torch.zeros_like(means[valid]) if flows is None else flows[valid],
        keyframes=torch.full((n,), keyframe, dtype=torch.int64, device=depth.device),
        cameras=cameras[valid],
    )
