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
from drivingscene.gaussians.assembly import gaussians_from_pixels
from drivingscene.gaussians.core import Gaussians
from drivingscene.gaussians.recon import Reconstruction
from drivingscene.geometry.se3 import invert_rigid
from drivingscene.models.pipeline import rigid_flows
from drivingscene.render.scene import render_gaussians
from drivingscene.render.sky import fit_sky_from_pixels


def refine_colors(
    depth: torch.Tensor,  # [V, H, W]
    intrinsics: torch.Tensor,  # [V, 3, 3]
    cam_to_world: torch.Tensor,  # [V, 4, 4]
    images: torch.Tensor,  # [V, H, W, 3]
    valid: torch.Tensor,  # [V, H, W]
    sky_sh: torch.Tensor,
    iterations: int,
) -> torch.Tensor:
    """Per-pixel colours ``[V, H, W, 3]`` whose splats re-render the input views (Van Cittert
    deconvolution: c <- c + (image - render(c))). Splatting blurs by the splat footprint and the
    renderer's low-pass; this undoes most of it, bounding what per-pixel colours can reach."""
    height, width = depth.shape[-2:]
    world_to_cam = invert_rigid(cam_to_world.double()).float()
    colors = images.clone()
    for _ in range(iterations):
        g = gaussians_from_pixels(depth, intrinsics, cam_to_world, colors, keyframe=0, valid=valid)
        rendered = render_gaussians(g, 0.0, world_to_cam, intrinsics, height, width, sky_sh=sky_sh).colors
        colors = colors + torch.where(valid[..., None], images - rendered, torch.zeros_like(images))
    return colors


def oracle_reconstruction(pair: FramePair, *, use_scene_flow: bool = True, refine: int = 1) -> Reconstruction:
    """Gaussians from ``gt_depth`` (and ``gt_scene_flow``) of both keyframes, in the world frame;
    ``refine`` deconvolution steps for the colours (0 = the pixel colours as they are)."""
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
        colors = refine_colors(depth[k], batch.intrinsics, c2w[k].float(), images, ~sky[k], sky_sh, refine)
        parts.append(
            gaussians_from_pixels(depth[k], batch.intrinsics, c2w[k].float(), colors, keyframe=k, flows=flows, valid=~sky[k])
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
