"""``drivingscene bench raster``: speed and peak memory of ``drivingscene.render.rasterize`` on CPU.

The scene is the one the model produces: one Gaussian per pixel of 6 surround views, unprojected
from a procedural depth map (ground plane, street walls, a few boxes, a far "sky" shell), scale
equal to the pixel footprint ``depth / focal``, rendered back into the same 6 views. Each
(size, backend) runs in a fresh process so that its peak RSS is its own; times are medians of
several runs after one warm-up. Prints a markdown table and writes it to ``--out``.
"""

from __future__ import annotations

import argparse
import math
import multiprocessing
import os
import platform
import resource
import statistics
import time
from pathlib import Path

import torch
from torch import Tensor

from drivingscene.geometry import invert_rigid

DEFAULT_SIZES = ("48x88", "96x176", "176x320")
# Axis-aligned boxes (x0, x1, y0, y1, z0, z1) in metres: parked cars and a kiosk.
BOXES = ((6.0, 10.5, 2.5, 4.5, 0.0, 1.6), (-9.0, -4.5, -5.0, -3.0, 0.0, 1.5), (2.0, 4.0, -6.0, -4.0, 0.0, 2.8))
STREET = (-30.0, 40.0, -7.0, 7.0, 9.0)  # x0, x1, y0, y1 of the building fronts, wall height
SKY_DISTANCE = 80.0


def surround_rig(height: int, width: int, num_views: int = 6, hfov_deg: float = 70.0) -> tuple[Tensor, Tensor]:
    """World-to-camera ``[V, 4, 4]`` and intrinsics ``[V, 3, 3]`` of a ring of cameras 1.5 m above the ground."""
    f = 0.5 * width / math.tan(math.radians(hfov_deg) / 2)
    Ks = torch.tensor([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1]]).repeat(num_views, 1, 1)
    cam_to_world = torch.eye(4).repeat(num_views, 1, 1)
    for v in range(num_views):
        yaw = 2 * math.pi * v / num_views
        fwd = torch.tensor([math.cos(yaw), math.sin(yaw), 0.0])
        right = torch.tensor([math.sin(yaw), -math.cos(yaw), 0.0])
        cam_to_world[v, :3, :3] = torch.stack([right, torch.tensor([0.0, 0.0, -1.0]), fwd], dim=1)
        cam_to_world[v, :3, 3] = torch.tensor([0.0, 0.0, 1.5])
    return invert_rigid(cam_to_world), Ks


def _ray_depth(origin: Tensor, dirs: Tensor) -> Tensor:
    """Ray parameter ``[R]`` of the first hit along ``dirs`` ``[R, 3]`` (camera z = 1 units)."""
    big = torch.full(dirs.shape[:1], float("inf"))
    t = torch.where(dirs[:, 2] < 0, -origin[2] / dirs[:, 2], big)  # ground z = 0
    x0, x1, y0, y1, wall_h = STREET
    for axis, plane in ((0, x0), (0, x1), (1, y0), (1, y1)):
        tp = (plane - origin[axis]) / dirs[:, axis]
        z = origin[2] + tp * dirs[:, 2]
        t = torch.where((tp > 0) & (z >= 0) & (z <= wall_h), torch.minimum(t, tp), t)
    for box in BOXES:
        lo = torch.tensor(box[0::2]) - origin
        hi = torch.tensor(box[1::2]) - origin
        t0, t1 = lo / dirs, hi / dirs
        near = torch.minimum(t0, t1).amax(-1)
        far = torch.maximum(t0, t1).amin(-1)
        t = torch.where((near <= far) & (near > 0), torch.minimum(t, near), t)
    sky = SKY_DISTANCE / dirs.norm(dim=-1)
    return torch.where(torch.isfinite(t), t, sky)


def surround_scene(height: int, width: int, seed: int = 0) -> dict[str, Tensor]:
    """Gaussians (one per pixel of 6 views) plus the cameras, as keyword arguments of ``rasterize``."""
    g = torch.Generator().manual_seed(seed)
    viewmats, Ks = surround_rig(height, width)
    cam_to_world = invert_rigid(viewmats)
    v, u = torch.meshgrid(torch.arange(height, dtype=torch.float32), torch.arange(width, dtype=torch.float32), indexing="ij")
    means, scales = [], []
    for k, c2w in zip(Ks, cam_to_world):
        d_cam = torch.stack([(u - k[0, 2]) / k[0, 0], (v - k[1, 2]) / k[1, 1], torch.ones_like(u)], -1).reshape(-1, 3)
        d_world = d_cam @ c2w[:3, :3].T
        depth = _ray_depth(c2w[:3, 3], d_world)  # camera z, metres
        means.append(c2w[:3, 3] + depth[:, None] * d_world)
        scales.append((depth / k[0, 0])[:, None] * (0.8 + 0.4 * torch.rand(len(depth), 3, generator=g)))
    n = sum(len(m) for m in means)
    return dict(
        means=torch.cat(means),
        quats=torch.randn(n, 4, generator=g),
        scales=torch.cat(scales),
        opacities=0.5 + 0.49 * torch.rand(n, generator=g),
        colors=torch.rand(n, 3, generator=g),
        viewmats=viewmats,
        Ks=Ks,
        width=width,
        height=height,
    )
