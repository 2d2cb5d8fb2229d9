"""Rendering Gaussians of a frame pair at a time t into cameras, over the sky background."""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from drivingscene.errors import InputError
from drivingscene.gaussians.core import DEFAULT_BLEND, Gaussians, sh0_to_rgb
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
    blend: str = "all",  # how both keyframes' Gaussians combine at t (Gaussians.time_weights, "layers")
    **raster_kwargs,
) -> RenderOutput:
    """Colour, depth and alpha ``[B, H, W, ...]`` of the Gaussians moved to normalised time t."""
    if blend == "layers":
        return render_layers(
            gaussians, t, world_to_cam, intrinsics, height, width, sky_sh=sky_sh, background=background, **raster_kwargs
        )
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


# "layers": the weight of the other keyframe's layer at a keyframe itself, so that what the near
# layer did not see (its holes: alpha < 1) comes from the far one.
LAYER_FLOOR = 0.05


def render_layers(
    gaussians: Gaussians,
    t: float | Tensor,
    world_to_cam: Tensor,  # [B, 4, 4]
    intrinsics: Tensor,  # [B, 3, 3]
    height: int,
    width: int,
    **kwargs,
) -> RenderOutput:
    """Each keyframe's Gaussians rendered on their own at time t (occlusion within a keyframe's set
    only), the two images blended per pixel with weights ``(1 - t + f) alpha_0`` and
    ``(t + f) alpha_1`` (f = ``LAYER_FLOOR``): where both layers see a surface they cross-fade in
    time, where one has a hole the other fills it. Rendering both sets together ("all") lets the
    nearer of two slightly misplaced copies of a surface win outright, which doubles edges; the
    blend degrades to a cross-fade instead (docs/results.md measures both)."""
    layers = [
        render_gaussians(gaussians.index(gaussians.keyframes == k), t, world_to_cam, intrinsics, height, width, blend="all", **kwargs)
        for k in (0, 1)
    ]
    t = float(t)
    w0 = (1.0 - t + LAYER_FLOOR) * layers[0].alphas
    w1 = (t + LAYER_FLOOR) * layers[1].alphas
    total = w0 + w1
    empty = total < 1e-6  # neither layer covers the pixel: both show the background
    w0 = torch.where(empty, torch.full_like(w0, 0.5), w0)
    w1 = torch.where(empty, torch.full_like(w1, 0.5), w1)
    total = w0 + w1
    colors = (w0[..., None] * layers[0].colors + w1[..., None] * layers[1].colors) / total[..., None]
    depths = (w0 * layers[0].depths + w1 * layers[1].depths) / total
    return RenderOutput(colors=colors, depths=depths, alphas=torch.maximum(layers[0].alphas, layers[1].alphas))


def render_eval_frames(recon, pair, blend: str = DEFAULT_BLEND, **raster_kwargs) -> Tensor:
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


def render_input_views(recon, pair, blend: str = DEFAULT_BLEND, **raster_kwargs) -> Tensor:
    """Renders ``[2, V, H, W, 3]`` of a reconstruction at its own keyframes, each camera at the
    pose and time its input image was taken: how well the Gaussians reproduce their inputs."""
    height, width = pair.image_size
    cams = torch.from_numpy(np.array(pair.camera_ego_poses())) @ torch.from_numpy(pair.cam_to_ego).double()
    k = torch.from_numpy(pair.intrinsics).float()
    times = np.repeat([[0.0], [1.0]], pair.num_views, 1) if pair.camera_timestamps is None else pair.normalised_time(pair.camera_timestamps)
    g = recon.visible()
    frames = torch.empty(2, pair.num_views, height, width, 3)
    for key in (0, 1):
        # cameras taken at one time render together; otherwise each at its own time
        groups = [list(range(pair.num_views))] if np.ptp(times[key]) == 0 else [[v] for v in range(pair.num_views)]
        for views in groups:
            out = render_gaussians(
                g, float(times[key][views[0]]), invert_rigid(cams[key][views]), k[views], height, width,
                sky_sh=recon.sky_sh, blend=blend, **raster_kwargs,
            )
            frames[key, views] = out.colors.clamp(0, 1)
    return frames

