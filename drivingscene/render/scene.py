"""Rendering Gaussians of a frame pair at a time t into cameras, over the sky background."""

from __future__ import annotations

import torch
from torch import Tensor

from drivingscene.gaussians.core import Gaussians
from drivingscene.render.rasterize import RenderOutput, rasterize
from drivingscene.render.sky import ray_directions, sky_colors


def render_gaussians(
    gaussians: Gaussians,
    t: float | Tensor,
    world_to_cam: Tensor,  # [B, 4, 4]
    intrinsics: Tensor,  # [B, 3, 3]
    height: int,
    width: int,
    *,
    sky_sh: Tensor | None = None,  # [K, 3]
    background: Tensor | None = None,  # [3], used when there is no sky model
    **raster_kwargs,
) -> RenderOutput:
    """Colour, depth and alpha ``[B, H, W, ...]`` of the Gaussians moved to normalised time t."""
    g = gaussians
    degree = g.sh_degree
    colors = g.colors() if degree == 0 else g.sh
    out = rasterize(
        g.means_at(t),
        g.quats,
        g.scales,
        g.opacities,
        colors,
        world_to_cam.float(),
        intrinsics.float(),
        width,
        height,
        background=None if sky_sh is not None else background,
        sh_degree=None if degree == 0 else degree,
        **raster_kwargs,
    )
    if sky_sh is None:
        return out
    cam_to_world = torch.linalg.inv(world_to_cam.double()).float()
    sky = sky_colors(sky_sh, ray_directions(cam_to_world, intrinsics.float(), height, width))
    return RenderOutput(colors=out.colors + (1 - out.alphas[..., None]) * sky, depths=out.depths, alphas=out.alphas)
