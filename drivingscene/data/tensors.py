"""A frame pair as float tensors in a local frame, ready for the networks.

Poses are re-expressed relative to the ego pose at keyframe 0 (in float64, then cast), so float32
stays precise even when world coordinates are large (map or UTM frames). ``local_to_world`` maps
results back.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from drivingscene.data.frame_pair import FramePair


@dataclass
class PairTensors:
    images: Tensor  # [2, V, 3, H, W] float in [0, 1]
    intrinsics: Tensor  # [V, 3, 3]
    cam_to_ego: Tensor  # [V, 4, 4]
    cam_to_local: Tensor  # [2, V, 4, 4] camera poses in the local frame (ego at keyframe 0)
    local_to_world: Tensor  # [4, 4] float64
    eval_images: Tensor | None = None  # [M, V, 3, H, W]
    eval_cam_to_local: Tensor | None = None  # [M, V, 4, 4]
    eval_times: Tensor | None = None  # [M] normalised time in [0, 1]
    gt_depth: Tensor | None = None  # [2, V, H, W]
    gt_flow: Tensor | None = None  # [2, V, H, W, 2]
    gt_dynamic: Tensor | None = None  # [2, V, H, W] bool
    valid_mask: Tensor | None = None  # [V, H, W] bool: pixels that see the world (None: all)
    eval_camera_times: Tensor | None = None  # [M, V] normalised capture time of each intermediate image
    # `resized_images`, per size (not an init field: `dataclasses.replace` starts a fresh cache)
    _resized: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    @property
    def num_views(self) -> int:
        return int(self.images.shape[1])

    @property
    def image_size(self) -> tuple[int, int]:
        return int(self.images.shape[-2]), int(self.images.shape[-1])

    def resized_images(self, size: tuple[int, int]) -> Tensor:
        """``images`` area-resized to ``size`` ``[2, V, 3, h, w]``, computed once per size (the
        networks and the search all run on the images at the networks' input size)."""
        size = (int(size[0]), int(size[1]))
        if size == self.image_size:
            return self.images
        source, version, small = self._resized.get(size, (None, None, None))
        if source is not self.images or version != self.images._version:  # new or changed images
            small = F.interpolate(self.images.flatten(0, 1), size=size, mode="area").unflatten(0, self.images.shape[:2])
            self._resized[size] = (self.images, self.images._version, small)
        return small

    def to(self, device) -> PairTensors:
        return PairTensors(
            **{
                f.name: None if getattr(self, f.name) is None else getattr(self, f.name).to(device)
                for f in fields(self)
                if f.init
            }
        )


def world_cameras(batch: PairTensors) -> Tensor:
    """Camera-to-world ``[2, V, 4, 4]`` of both keyframes, in float64."""
    return batch.local_to_world[None, None] @ batch.cam_to_local.double()


def _images(array: np.ndarray) -> Tensor:
    """uint8 [..., H, W, 3] -> float [..., 3, H, W] in [0, 1]."""
    return torch.from_numpy(np.ascontiguousarray(np.moveaxis(array, -1, -3))).float() / 255.0


def pair_to_tensors(pair: FramePair, *, with_gt: bool = True, with_eval: bool = True) -> PairTensors:
    world_to_local = np.linalg.inv(pair.ego_to_world[0])
    # each image's own capture pose (cameras of a keyframe need not be simultaneous)
    cam_to_ego = pair.cam_to_ego.astype(np.float64)
    cam_to_local = world_to_local[None, None] @ pair.camera_ego_poses() @ cam_to_ego[None]
    out = PairTensors(
        images=_images(pair.images),
        intrinsics=torch.from_numpy(pair.intrinsics.astype(np.float32)),
        cam_to_ego=torch.from_numpy(pair.cam_to_ego.astype(np.float32)),
        cam_to_local=torch.from_numpy(cam_to_local.astype(np.float32)),
        local_to_world=torch.from_numpy(pair.ego_to_world[0].copy()),
    )
    if with_eval and pair.num_eval:
        eval_c2l = world_to_local[None, None] @ pair.eval_camera_ego_poses() @ cam_to_ego[None]
        out.eval_images = _images(pair.eval_images)
        out.eval_cam_to_local = torch.from_numpy(eval_c2l.astype(np.float32))
        out.eval_times = torch.from_numpy(pair.normalised_time(pair.eval_timestamps).astype(np.float32))
        out.eval_camera_times = torch.from_numpy(pair.eval_camera_times().astype(np.float32))
    if pair.valid_mask is not None:
        out.valid_mask = torch.from_numpy(pair.valid_mask)
    if with_gt:
        if pair.gt_depth is not None:
            out.gt_depth = torch.from_numpy(pair.gt_depth)
        if pair.gt_flow is not None:
            out.gt_flow = torch.from_numpy(pair.gt_flow)
        if pair.gt_dynamic is not None:
            out.gt_dynamic = torch.from_numpy(pair.gt_dynamic)
    return out
