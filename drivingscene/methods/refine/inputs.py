"""What refinement may read of a frame pair: the two keyframes' input images, the rig, each image's
capture pose and time, the pixels that see the world, and LiDAR only when asked.

Everything is expressed in the pair's local frame (ego at keyframe 0), where float32 keeps its
precision whatever the world coordinates. The intermediate frames (``eval_*``) are never read:
`refine_inputs` is the only place refinement touches the pair, and it does not look at them.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from drivingscene.data.frame_pair import FramePair
from drivingscene.errors import InputError
from drivingscene.gaussians.recon import Reconstruction
from drivingscene.geometry.camera import scale_intrinsics


@dataclass(frozen=True)
class RefineInputs:
    """The input views of a pair (keyframe-major), float32 tensors in the local frame."""

    images: Tensor  # [2, V, 3, H, W] in [0, 1]
    intrinsics: Tensor  # [V, 3, 3]
    cam_to_ego: Tensor  # [V, 4, 4]
    cam_to_local: Tensor  # [2, V, 4, 4] each image's capture pose
    times: Tensor  # [2, V] each image's normalised capture time (0 and 1 for a simultaneous rig)
    local_to_world: Tensor  # [4, 4] float64
    valid: Tensor | None  # [V, H, W] bool: pixels that see the world (None: all)
    lidar: Tensor | None  # [2, V, H, W] LiDAR z-depth, 0 where none (only with ``lidar=True``)

    @property
    def num_views(self) -> int:
        return int(self.images.shape[1])

    @property
    def image_size(self) -> tuple[int, int]:
        return int(self.images.shape[-2]), int(self.images.shape[-1])

    @property
    def world_to_local(self) -> Tensor:
        return torch.linalg.inv(self.local_to_world)


def refine_inputs(pair: FramePair, lidar: bool = False) -> RefineInputs:
    """The input views of ``pair`` (never its ``eval_*`` frames); ``lidar`` adds ``gt_depth`` and
    raises a one-line error when the scene has none."""
    if lidar and pair.gt_depth is None:
        raise InputError("--lidar: the scene has no LiDAR depth (gt_depth); import it with LiDAR or drop --lidar")
    world_to_local = np.linalg.inv(pair.ego_to_world[0])
    cam_to_ego = pair.cam_to_ego.astype(np.float64)
    cam_to_local = world_to_local[None, None] @ pair.camera_ego_poses() @ cam_to_ego[None]
    if pair.camera_timestamps is not None:
        times = pair.normalised_time(pair.camera_timestamps)
    else:
        times = np.broadcast_to(np.array([[0.0], [1.0]]), (2, pair.num_views))
    images = np.ascontiguousarray(np.moveaxis(pair.images, -1, -3))
    return RefineInputs(
        images=torch.from_numpy(images).float() / 255.0,
        intrinsics=torch.from_numpy(pair.intrinsics.astype(np.float32)),
        cam_to_ego=torch.from_numpy(pair.cam_to_ego.astype(np.float32)),
        cam_to_local=torch.from_numpy(cam_to_local.astype(np.float32)),
        times=torch.from_numpy(np.array(times, dtype=np.float32)),
        local_to_world=torch.from_numpy(pair.ego_to_world[0].copy()),
        valid=None if pair.valid_mask is None else torch.from_numpy(pair.valid_mask.copy()),
        lidar=torch.from_numpy(pair.gt_depth.copy()).float() if lidar else None,
    )


def scaled_inputs(inputs: RefineInputs, scale: float) -> RefineInputs:
    """The input views at ``scale`` of their size (at least 4x4): images area-resized, intrinsics
    scaled, a pixel valid where every pixel it covers is, a LiDAR return kept at the nearest return
    within the pixel; ``inputs`` itself at their own size."""
    height, width = inputs.image_size
    size = (max(4, round(height * scale)), max(4, round(width * scale)))
    if size == (height, width):
        return inputs
    images = F.interpolate(inputs.images.flatten(0, 1), size=size, mode="area").view(2, inputs.num_views, 3, *size)
    valid = lidar = None
    if inputs.valid is not None:
        valid = F.interpolate((~inputs.valid)[:, None].float(), size=size, mode="area")[:, 0] == 0
    if inputs.lidar is not None:
        far = torch.where(inputs.lidar > 0, inputs.lidar, torch.full_like(inputs.lidar, 1e9)).flatten(0, 1)
        lidar = -F.adaptive_max_pool2d(-far[:, None], size)[:, 0]
        lidar = torch.where(lidar < 1e8, lidar, torch.zeros_like(lidar)).view(2, inputs.num_views, *size)
    intrinsics = scale_intrinsics(inputs.intrinsics, size[1] / width, size[0] / height)
    return replace(inputs, images=images, intrinsics=intrinsics, valid=valid, lidar=lidar)


def pair_from_reconstruction(recon: Reconstruction) -> FramePair:
    """A frame pair with a reconstruction's input images, rig and keyframe poses (for refining a
    saved ``recon.npz`` without its scene: no per-image capture poses, no LiDAR)."""
    if recon.images is None or recon.num_views == 0:
        raise InputError("refine: the reconstruction carries no input images; refine it from its scene.npz")
    return FramePair(
        images=recon.images,
        intrinsics=recon.intrinsics,
        cam_to_ego=recon.cam_to_ego,
        ego_to_world=recon.ego_to_world,
        timestamps=recon.timestamps,
        camera_names=recon.camera_names,
        valid_mask=recon.valid_mask,
    )
