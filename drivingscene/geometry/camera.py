"""Pinhole cameras in OpenCV axes. Pixel centres sit at integer coordinates."""

from __future__ import annotations

import torch
from torch import Tensor


def pixel_grid(height: int, width: int, *, dtype=torch.float32, device=None) -> Tensor:
    """Pixel-centre coordinates ``[H, W, 2]`` as (u, v) = (column, row)."""
    v, u = torch.meshgrid(
        torch.arange(height, dtype=dtype, device=device),
        torch.arange(width, dtype=dtype, device=device),
        indexing="ij",
    )
    return torch.stack([u, v], dim=-1)


def unproject(depth: Tensor, intrinsics: Tensor) -> Tensor:
    """Back-project z-depth maps to camera-frame points.

    Args:
        depth: ``[..., H, W]`` z-depth in metres.
        intrinsics: ``[..., 3, 3]`` pixels.

    Returns:
        ``[..., H, W, 3]`` points in camera axes (x right, y down, z forward).
    """
    height, width = depth.shape[-2:]
    uv = pixel_grid(height, width, dtype=depth.dtype, device=depth.device)
    k = intrinsics[..., None, None, :, :]
    fx, fy, cx, cy, skew = k[..., 0, 0], k[..., 1, 1], k[..., 0, 2], k[..., 1, 2], k[..., 0, 1]
    y = (uv[..., 1] - cy) / fy
    x = (uv[..., 0] - cx - skew * y) / fx
    return torch.stack([x * depth, y * depth, depth], dim=-1)


def project(points: Tensor, intrinsics: Tensor, eps: float = 1e-6) -> tuple[Tensor, Tensor]:
    """Project camera-frame points ``[..., N, 3]`` with ``[..., 3, 3]`` intrinsics.

    Returns:
        uv ``[..., N, 2]`` pixels and z ``[..., N]`` depth. Points with z <= eps get uv from a
        clamped z; callers mask them with ``z > eps``.
    """
    z = points[..., 2]
    zc = z.clamp(min=eps)
    k = intrinsics[..., None, :, :]
    x, y = points[..., 0] / zc, points[..., 1] / zc
    u = k[..., 0, 0] * x + k[..., 0, 1] * y + k[..., 0, 2]
    v = k[..., 1, 1] * y + k[..., 1, 2]
    return torch.stack([u, v], dim=-1), z


def scale_intrinsics(intrinsics: Tensor, scale_x: float, scale_y: float) -> Tensor:
    """Intrinsics ``[..., 3, 3]`` for an image resized by (scale_x, scale_y).

    With pixel centres at integers, u' + 0.5 = (u + 0.5) * s, so c' = (c + 0.5) * s - 0.5.
    """
    out = intrinsics.clone()
    out[..., 0, 0] *= scale_x
    out[..., 0, 1] *= scale_x
    out[..., 1, 1] *= scale_y
    out[..., 0, 2] = (intrinsics[..., 0, 2] + 0.5) * scale_x - 0.5
    out[..., 1, 2] = (intrinsics[..., 1, 2] + 0.5) * scale_y - 0.5
    return out
