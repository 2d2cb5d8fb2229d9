"""The depth a rig's mounting alone implies: where each pixel's ray meets the road plane (the ego
frame's z = 0). Inference uses it as a guide where D's shape is off (`methods.matched_depth`), the
classical method and the rig check as a prior, the benchmarks as a baseline (`eval.baselines`)."""

from __future__ import annotations

import numpy as np
import torch

from drivingscene.data.frame_pair import FramePair


def road_plane_depth(pair: FramePair, far: float = 80.0) -> np.ndarray:
    """``[2, V, H, W]`` float32 z-depth where each pixel's ray meets the ego frame's z = 0 plane,
    ``far`` where it does not within ``far`` (at and above the horizon, or a camera mounted below z = 0)."""
    from drivingscene.geometry.camera import unproject

    height, width = pair.image_size
    rays = unproject(torch.ones(pair.num_views, height, width), torch.from_numpy(pair.intrinsics).float())  # z = 1
    cam_to_ego = torch.from_numpy(pair.cam_to_ego).float()
    down = -torch.einsum("vj,vhwj->vhw", cam_to_ego[:, 2, :3], rays)  # metres the ray drops per metre of depth
    mount = cam_to_ego[:, 2, 3].view(-1, 1, 1)  # camera height above z = 0
    depth = torch.where((down > 0) & (mount > 0), mount / down.clamp(min=1e-9), torch.full_like(down, far)).clamp(max=far)
    return np.broadcast_to(depth.numpy().astype(np.float32), (2, *depth.shape)).copy()
