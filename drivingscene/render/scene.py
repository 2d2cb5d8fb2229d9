"""Rendering Gaussians of a frame pair at a time t into cameras, over the sky background."""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from drivingscene.errors import InputError
from drivingscene.gaussians.core import Gaussians, sh0_to_rgb
from drivingscene.geometry.se3 import invert_rigid
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
    blend: str = "all",  # how both keyframes' Gaussians combine at t (Gaussians.time_weights)
    **raster_kwargs,
) -> RenderOutput:
    """Colour, depth and alpha ``[B, H, W, ...]`` of the Gaussians moved to normalised time t."""
    g = gaussians
    opacities = g.opacities * g.time_weights(t, blend)
    degree = g.sh_degree
    # 3DGS colour: max(SH + 0.5, 0), no upper clamp (degree 0 is passed as plain RGB).
    colors = torch.clamp_min(sh0_to_rgb(g.sh[:, 0]), 0.0) if degree == 0 else g.sh
    out = rasterize(
        g.means_at(t),
        g.quats,
        g.scales,
        opacities,
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


def render_eval_frames(recon, pair, blend: str = "all", **raster_kwargs) -> Tensor:
    """Renders ``[M, V, H, W, 3]`` of a reconstruction at the scene's intermediate frames, each
    camera at the exact ego pose and time recorded for its image (not interpolated)."""
    if pair.num_eval == 0:
        raise InputError("the scene has no intermediate frames (eval_images) to render")
    height, width = recon.image_size
    cam_to_ego = torch.from_numpy(recon.cam_to_ego).double()
    k = torch.from_numpy(recon.intrinsics).float()
    g = recon.visible()
    egos = torch.from_numpy(np.array(pair.eval_camera_ego_poses()))  # [M, V, 4, 4] (a copy: may be a broadcast view)
    times = pair.eval_camera_times()  # [M, V]
    frames = []
    for m in range(pair.num_eval):
        world_to_cam = invert_rigid(egos[m] @ cam_to_ego)
        # cameras taken at one time render together; otherwise each at its own time
        groups = [list(range(len(times[m])))] if np.ptp(times[m]) == 0 else [[v] for v in range(len(times[m]))]
        colors = torch.empty(len(times[m]), height, width, 3)
        for views in groups:
            out = render_gaussians(
                g,
                float(times[m][views[0]]),
                world_to_cam[views],
                k[views],
                height,
                width,
                sky_sh=recon.sky_sh,
                blend=blend,
                **raster_kwargs,
            )
            colors[views] = out.colors.clamp(0, 1)
        frames.append(colors)
    return torch.stack(frames)
