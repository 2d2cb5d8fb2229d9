"""The oracle: per-pixel Gaussians from ground-truth depth and scene flow, assembled exactly as the
model assembles its predictions. It bounds what the representation and renderer can reach, and
gives the viewer real content without a trained model.
"""

from __future__ import annotations

import time

import numpy as np
import torch

from drivingscene.data.frame_pair import FramePair
from drivingscene.data.tensors import pair_to_tensors
from drivingscene.errors import InputError
from drivingscene.gaussians.assembly import gaussians_from_pixels
from drivingscene.gaussians.core import Gaussians
from drivingscene.gaussians.recon import Reconstruction
from drivingscene.models.pipeline import rigid_flows
from drivingscene.render.sky import fit_sky, ray_directions


def _world_cameras(batch) -> torch.Tensor:
    """Camera-to-world ``[2, V, 4, 4]`` in float64."""
    return batch.local_to_world[None, None] @ batch.cam_to_local.double()


def fit_sky_from_pixels(images: torch.Tensor, sky: torch.Tensor, cam_to_world: torch.Tensor, intrinsics: torch.Tensor) -> torch.Tensor:
    """Sky SH ``[K, 3]`` from images ``[T, V, 3, H, W]`` where ``sky`` ``[T, V, H, W]`` is true."""
    height, width = images.shape[-2:]
    dirs = ray_directions(cam_to_world.flatten(0, 1), intrinsics.repeat(images.shape[0], 1, 1).double(), height, width)
    colors = images.flatten(0, 1).permute(0, 2, 3, 1)
    mask = sky.flatten(0, 1)
    return fit_sky(dirs[mask].float(), colors[mask]).float()


def oracle_reconstruction(pair: FramePair, *, use_scene_flow: bool = True) -> Reconstruction:
    """Gaussians from ``gt_depth`` (and ``gt_scene_flow``) of both keyframes, in the world frame."""
    if pair.gt_depth is None:
        raise InputError("oracle: the scene has no gt_depth; the oracle needs ground-truth depth")
    if use_scene_flow and pair.gt_scene_flow is None:
        raise InputError("oracle: the scene has no gt_scene_flow; pass --no-flow for a static oracle")
    start = time.perf_counter()
    batch = pair_to_tensors(pair, with_eval=False)
    depth = batch.gt_depth
    sky = depth <= 0
    c2w = _world_cameras(batch)
    parts = []
    for k in (0, 1):
        flows = torch.from_numpy(pair.gt_scene_flow[k]) if use_scene_flow else None
        parts.append(
            gaussians_from_pixels(
                depth[k],
                batch.intrinsics,
                c2w[k].float(),
                batch.images[k].permute(0, 2, 3, 1),
                keyframe=k,
                flows=flows,
                valid=~sky[k],
            )
        )
    gaussians = Gaussians.cat(parts)
    sky_sh = fit_sky_from_pixels(batch.images, sky, c2w, batch.intrinsics)
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
        meta={"method": "oracle", "scene_flow": use_scene_flow, "seconds": round(time.perf_counter() - start, 4)},
    )
