"""The oracle: per-pixel Gaussians from ground-truth depth and scene flow, assembled exactly as the
model assembles its predictions. It bounds what the representation and renderer can reach, and
gives the viewer real content without a trained model.
"""

from __future__ import annotations

import time

import numpy as np
import torch

from drivingscene.data.frame_pair import FramePair
from drivingscene.data.tensors import pair_to_tensors, world_cameras
from drivingscene.errors import InputError
from drivingscene.gaussians.assembly import (
    DEFAULT_OPACITY,
    RAY_EXTENT,
    extend_along_rays,
    gaussians_from_pixels,
    pixel_footprints,
    surfel_frames,
)
from drivingscene.gaussians.core import Gaussians
from drivingscene.gaussians.recon import Reconstruction
from drivingscene.models.pipeline import rigid_flows
from drivingscene.render.color_solve import ITERATIONS as COLOR_ITERATIONS
from drivingscene.render.color_solve import solve_pixel_colors
from drivingscene.render.sky import fit_sky_from_pixels


def surfel_maps(depth: torch.Tensor, intrinsics: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Default surfels of depth maps ``[V, H, W]`` as `gaussians_from_pixels` makes them, footprint
    rule included: camera-axis quaternions ``[V, H, W, 4]`` and log scales ``[V, H, W, 3]``."""
    quats, log_scales = surfel_frames(depth, intrinsics)
    return quats, pixel_footprints(depth, intrinsics, quats, log_scales)


def refine_colors(
    depth: torch.Tensor,  # [V, H, W]
    intrinsics: torch.Tensor,  # [V, 3, 3]
    images: torch.Tensor,  # [V, H, W, 3]
    valid: torch.Tensor,  # [V, H, W]
    iterations: int,
    surfels: tuple[torch.Tensor, torch.Tensor] | None = None,  # `surfel_maps` when already made
) -> torch.Tensor:
    """Per-pixel colours ``[V, H, W, 3]`` whose default surfels re-render each input image in its
    own layer: the colour solve of `render.color_solve` (the deconvolution of the splatting blur)."""
    if iterations <= 0:
        return images
    quats, log_scales = surfels if surfels is not None else surfel_maps(depth, intrinsics)
    opacities = torch.full_like(depth, DEFAULT_OPACITY)
    return solve_pixel_colors(depth, intrinsics, quats, log_scales, opacities, images, images, valid, iterations)


def oracle_reconstruction(
    pair: FramePair, *, use_scene_flow: bool = True, refine: int = COLOR_ITERATIONS, ray_extent: float = RAY_EXTENT
) -> Reconstruction:
    """Gaussians from ``gt_depth`` (and ``gt_scene_flow``) of both keyframes, in the world frame;
    ``refine`` iterations of the colour solve (0 = the pixel colours as they are); each Gaussian
    extended along its view ray by ``ray_extent`` (`gaussians.assembly.extend_along_rays`, as the model's)."""
    if pair.gt_depth is None:
        raise InputError("oracle: the scene has no gt_depth; the oracle needs ground-truth depth")
    if use_scene_flow and pair.gt_scene_flow is None:
        raise InputError("oracle: the scene has no gt_scene_flow; pass --no-flow for a static oracle")
    start = time.perf_counter()
    batch = pair_to_tensors(pair, with_eval=False)
    depth = batch.gt_depth
    sky = depth <= 0
    c2w = world_cameras(batch)
    if batch.valid_mask is not None:  # the ego's body is neither sky nor a Gaussian
        sky_sh = fit_sky_from_pixels(batch.images, sky & batch.valid_mask, c2w, batch.intrinsics)
        sky = sky | ~batch.valid_mask
    else:
        sky_sh = fit_sky_from_pixels(batch.images, sky, c2w, batch.intrinsics)
    parts = []
    for k in (0, 1):
        flows = torch.from_numpy(pair.gt_scene_flow[k]) if use_scene_flow else None
        images = batch.images[k].permute(0, 2, 3, 1)
        quats, log_scales = surfel_maps(depth[k], batch.intrinsics)
        colors = refine_colors(depth[k], batch.intrinsics, images, ~sky[k], refine, (quats, log_scales))
        quats, log_scales = extend_along_rays(depth[k], batch.intrinsics, quats, log_scales, ray_extent)
        parts.append(
            gaussians_from_pixels(
                depth[k],
                batch.intrinsics,
                c2w[k].float(),
                colors,
                keyframe=k,
                flows=flows,
                valid=~sky[k],
                quats=quats,
                log_scales=log_scales,
                footprints=None,
            )
        )
    gaussians = Gaussians.cat(parts)
    rigid = torch.where(sky[..., None], 0.0, rigid_flows(depth, batch))
    residual = None
    if pair.gt_flow is not None:
        residual = torch.where(sky[..., None], 0.0, torch.from_numpy(pair.gt_flow) - rigid).numpy()
    return Reconstruction.from_pair(
        pair,
        gaussians,
        sky_sh=sky_sh,
        depth=pair.gt_depth,
        rigid_flow=rigid.numpy().astype(np.float32),
        residual_flow=residual,
        meta={
            "method": "oracle",
            "scene_flow": use_scene_flow,
            "refine": refine,
            "timings": {"total_s": round(time.perf_counter() - start, 4)},
        },
    )
