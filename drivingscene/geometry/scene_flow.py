"""Lifting 2D optical flow and depth at two times to 3D world displacements."""

from __future__ import annotations

import torch
from torch import Tensor

from drivingscene.geometry.camera import pixel_grid
from drivingscene.geometry.se3 import matvec, transform_points


def _unproject_at(uv: Tensor, depth: Tensor, intrinsics: Tensor) -> Tensor:
    """Camera points ``[..., P, 3]`` at pixel positions uv ``[..., P, 2]`` with z-depth ``[..., P]``."""
    k = intrinsics[..., None, :, :]
    y = (uv[..., 1] - k[..., 1, 2]) / k[..., 1, 1]
    x = (uv[..., 0] - k[..., 0, 2] - k[..., 0, 1] * y) / k[..., 0, 0]
    return torch.stack([x * depth, y * depth, depth], dim=-1)


def scene_flow_from_optical_flow(
    depth_src: Tensor,  # [V, H, W] z-depth at the source keyframe
    depth_dst: Tensor,  # [V, H, W] z-depth at the destination keyframe
    flow: Tensor,  # [V, H, W, 2] source -> destination, pixels, same camera
    intrinsics: Tensor,  # [V, 3, 3]
    src_cam_to_world: Tensor,  # [V, 4, 4]
    dst_cam_to_world: Tensor,  # [V, 4, 4]
) -> tuple[Tensor, Tensor]:
    """World displacement of the surface seen at each source pixel.

    The source point is lifted with ``depth_src``; its destination is the pixel ``p + flow``
    lifted with ``depth_dst`` sampled there (nearest pixel, so depth edges are not blended).

    Returns:
        scene_flow ``[V, H, W, 3]`` metres and valid ``[V, H, W]`` (destination inside the image
        and both depths positive). Invalid entries are zero.
    """
    num_views, height, width = depth_src.shape
    grid = pixel_grid(height, width, dtype=depth_src.dtype, device=depth_src.device).expand(num_views, -1, -1, -1)
    dst_uv = grid + flow
    col = dst_uv[..., 0].round().long()
    row = dst_uv[..., 1].round().long()
    inside = (col >= 0) & (col < width) & (row >= 0) & (row < height)
    flat = (row.clamp(0, height - 1) * width + col.clamp(0, width - 1)).flatten(1)
    d_dst = torch.gather(depth_dst.flatten(1), 1, flat).view(num_views, height, width)
    valid = inside & (depth_src > 0) & (d_dst > 0)
    src_world = transform_points(src_cam_to_world, _unproject_at(grid.flatten(1, 2), depth_src.flatten(1), intrinsics))
    dst_world = transform_points(dst_cam_to_world, _unproject_at(dst_uv.flatten(1, 2), d_dst.flatten(1), intrinsics))
    scene_flow = (dst_world - src_world).view(num_views, height, width, 3)
    return torch.where(valid[..., None], scene_flow, torch.zeros_like(scene_flow)), valid


def scene_flow_at_pixels(
    depth_src: Tensor,  # [V, H, W]
    depth_dst: Tensor,  # [V, H, W]
    flow: Tensor,  # [V, H, W, 2]
    intrinsics: Tensor,  # [V, 3, 3]
    src_cam_to_world: Tensor,  # [V, 4, 4]
    dst_cam_to_world: Tensor,  # [V, 4, 4]
    index: Tensor,  # [P] view of each chosen pixel
    pixels: Tensor,  # [P, 2] integer (u, v)
) -> tuple[Tensor, Tensor]:
    """`scene_flow_from_optical_flow` at chosen pixels only: ``[P, 3]`` and valid ``[P]``.

    Fastest with ``index`` sorted (as ``nonzero`` returns it): each camera's pixels are then one
    slice, transformed by one matrix product instead of a gathered matrix per pixel."""
    _, height, width = depth_src.shape
    u, v = pixels[:, 0], pixels[:, 1]
    dst_uv = pixels.to(flow.dtype) + flow[index, v, u]
    col, row = dst_uv[:, 0].round().long(), dst_uv[:, 1].round().long()
    inside = (col >= 0) & (col < width) & (row >= 0) & (row < height)
    d_src = depth_src[index, v, u]
    d_dst = depth_dst[index, row.clamp(0, height - 1), col.clamp(0, width - 1)]
    valid = inside & (d_src > 0) & (d_dst > 0)
    k = intrinsics[index]
    src = _unproject_at(pixels.to(flow.dtype)[:, None], d_src[:, None], k)[:, 0]
    dst = _unproject_at(dst_uv[:, None], d_dst[:, None], k)[:, 0]
    scene_flow = _transform_by_view(dst_cam_to_world, index, dst) - _transform_by_view(src_cam_to_world, index, src)
    return torch.where(valid[:, None], scene_flow, torch.zeros_like(scene_flow)), valid


def _transform_by_view(transforms: Tensor, index: Tensor, points: Tensor) -> Tensor:
    """``points`` ``[P, 3]`` of views ``index`` ``[P]`` through ``transforms`` ``[V, 4, 4]``."""
    if len(index) > 1 and bool((index[1:] >= index[:-1]).all()):
        counts = torch.bincount(index, minlength=len(transforms)).tolist()
        parts = [transform_points(t, p) for p, t in zip(points.split(counts), transforms)]
        return torch.cat(parts)
    return matvec(transforms[index, :3, :3], points, transforms[index, :3, 3])
