"""Rigid flow from depth and poses, backward warping and forward-backward consistency."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from drivingscene import kernels
from drivingscene.geometry.camera import pixel_grid, project, unproject
from drivingscene.geometry.se3 import invert_rigid, transform_points

# Forward/backward consistency (UnFlow): |f + b(p + f)|^2 < FB_ALPHA (|f|^2 + |b(p + f)|^2) + FB_BETA.
FB_ALPHA = 0.01
FB_BETA = 0.5


def cams_to_world(cam_to_ego: Tensor, ego_to_world: Tensor) -> Tensor:
    """Camera poses ``[..., V, 4, 4]`` from the rig ``[V, 4, 4]`` and ego poses ``[..., 4, 4]``."""
    return ego_to_world[..., None, :, :] @ cam_to_ego


def rigid_flow(
    depth: Tensor,  # [..., H, W] z-depth of the source frame, metres
    intrinsics: Tensor,  # [..., 3, 3]
    src_cam_to_world: Tensor,  # [..., 4, 4]
    dst_cam_to_world: Tensor,  # [..., 4, 4]
    dst_intrinsics: Tensor | None = None,  # [..., 3, 3], default: same as the source
) -> tuple[Tensor, Tensor]:
    """Optical flow of a static world seen by a moving camera (or into another camera).

    Each source pixel is lifted with its depth, moved into the destination camera and projected
    with the destination intrinsics. Returns flow ``[..., H, W, 2]`` in pixels and the
    destination z-depth ``[..., H, W]`` (<= 0 where the point falls behind the destination camera).
    Float32 CPU maps ``[B, H, W]`` without gradients go through one compiled pass (the same
    arithmetic; `drivingscene.kernels.rigid_flow_dense`).
    """
    height, width = depth.shape[-2:]
    src_to_dst = invert_rigid(dst_cam_to_world) @ src_cam_to_world
    dst_k = intrinsics if dst_intrinsics is None else dst_intrinsics
    if depth.dim() == 3 and intrinsics.shape == dst_k.shape == (len(depth), 3, 3) and src_to_dst.shape == (len(depth), 4, 4):
        if kernels.available(kernels.rigid_flow_dense, "auto", depth, intrinsics, src_to_dst, dst_k):
            return kernels.rigid_flow_dense(depth, intrinsics, src_to_dst, dst_k)
    points = unproject(depth, intrinsics).flatten(-3, -2)  # [..., HW, 3]
    uv, z = project(transform_points(src_to_dst, points), dst_k)
    grid = pixel_grid(height, width, dtype=depth.dtype, device=depth.device)
    flow = uv.unflatten(-2, (height, width)) - grid
    return flow, z.unflatten(-1, (height, width))


def _to_sample_grid(coords: Tensor, height: int, width: int) -> Tensor:
    """Pixel coordinates ``[B, H, W, 2]`` to grid_sample's [-1, 1] (align_corners=True)."""
    scale = coords.new_tensor([2.0 / max(width - 1, 1), 2.0 / max(height - 1, 1)])
    return coords * scale - 1.0


def backward_warp(image: Tensor, flow: Tensor, mode: str = "bilinear") -> tuple[Tensor, Tensor]:
    """Sample ``image`` ``[B, C, H, W]`` at ``p + flow(p)``; flow ``[B, H, W, 2]`` in pixels.

    Returns the warped image ``[B, C, H, W]`` and a mask ``[B, H, W]`` of samples inside the image.
    """
    height, width = image.shape[-2:]
    coords = pixel_grid(height, width, dtype=flow.dtype, device=flow.device) + flow
    warped = F.grid_sample(
        image, _to_sample_grid(coords, height, width).to(image.dtype), mode=mode, padding_mode="border", align_corners=True
    )
    return warped, inside_image(coords, height, width)


def forward_backward_consistency(
    flow_fw: Tensor,  # [B, H, W, 2] keyframe 0 -> 1 at keyframe-0 pixels
    flow_bw: Tensor,  # [B, H, W, 2] keyframe 1 -> 0 at keyframe-1 pixels
    alpha: float = FB_ALPHA,
    beta: float = FB_BETA,
) -> Tensor:
    """Pixels whose forward flow is undone by the backward flow (UnFlow's test), ``[B, H, W]`` bool.

    |f + b(p + f)|^2 < alpha (|f|^2 + |b(p + f)|^2) + beta, and p + f inside the image. Float32
    CPU flows without gradients go through one compiled pass (`drivingscene.kernels.fb_consistent`).
    """
    if flow_fw.dim() == 4 and kernels.available(kernels.fb_consistent, "auto", flow_fw, flow_bw):
        return kernels.fb_consistent(flow_fw, flow_bw, alpha, beta)
    bw_at_fw, inside = backward_warp(flow_bw.permute(0, 3, 1, 2), flow_fw)
    return _consistent(flow_fw, bw_at_fw.permute(0, 2, 3, 1), alpha, beta) & inside


def _consistent(fw: Tensor, bw_at_fw: Tensor, alpha: float, beta: float) -> Tensor:
    diff = (fw + bw_at_fw).square().sum(-1)
    return diff < alpha * (fw.square().sum(-1) + bw_at_fw.square().sum(-1)) + beta


def sample_bilinear(image: Tensor, index: Tensor, uv: Tensor) -> Tensor:
    """``image`` ``[B, H, W, C]`` at points ``uv`` ``[P, 2]`` of images ``index`` ``[P]``, bilinear
    with border clamping (what `backward_warp` computes at every pixel, here at chosen points)."""
    _, height, width, channels = image.shape
    x = uv[:, 0].clamp(0, width - 1)
    y = uv[:, 1].clamp(0, height - 1)
    x0 = x.detach().floor().clamp(max=max(width - 2, 0))
    y0 = y.detach().floor().clamp(max=max(height - 2, 0))
    wx, wy = (x - x0)[:, None], (y - y0)[:, None]
    x0, y0 = x0.long(), y0.long()
    x1, y1 = (x0 + 1).clamp(max=width - 1), (y0 + 1).clamp(max=height - 1)
    flat = image.reshape(-1, channels)
    base = index * (height * width)

    def at(r: Tensor, c: Tensor) -> Tensor:
        return flat.index_select(0, base + r * width + c)

    top = at(y0, x0) * (1 - wx) + at(y0, x1) * wx
    bottom = at(y1, x0) * (1 - wx) + at(y1, x1) * wx
    return top * (1 - wy) + bottom * wy


def vector_length(v: Tensor) -> Tensor:
    """``[...]``: the length of each 2-vector of ``v`` ``[..., 2]`` (``hypot``: elementwise, about
    twice as fast on the CPU as ``norm(dim=-1)`` over a last axis of 2; equal up to float rounding)."""
    return torch.hypot(v[..., 0], v[..., 1])


def inside_image(uv: Tensor, height: int, width: int) -> Tensor:
    """Points ``uv`` ``[..., 2]`` (pixel coordinates) that fall inside an ``height`` x ``width`` image."""
    u, v = uv[..., 0], uv[..., 1]
    return (u >= -0.5) & (u <= width - 0.5) & (v >= -0.5) & (v <= height - 0.5)


def forward_backward_consistency_at(
    flow_fw: Tensor, flow_bw: Tensor, index: Tensor, pixels: Tensor, alpha: float = FB_ALPHA, beta: float = FB_BETA
) -> Tensor:
    """`forward_backward_consistency` at chosen pixels only: ``index`` ``[P]`` images, ``pixels``
    ``[P, 2]`` integer (u, v); flows ``[B, H, W, 2]``. Returns ``[P]`` bool."""
    height, width = flow_fw.shape[1:3]
    fw = flow_fw[index, pixels[:, 1], pixels[:, 0]]
    uv = pixels.to(fw.dtype) + fw
    return _consistent(fw, sample_bilinear(flow_bw, index, uv), alpha, beta) & inside_image(uv, height, width)
