"""Two trivial baselines for the in-between frame, with no geometry: what a method must beat.

- copy the nearest keyframe: each camera's eval image predicted by that camera's keyframe image
  nearest in time (t <= 0.5: keyframe 0);
- blend the two keyframes: (1 - t) I_0 + t I_1 per pixel.

t is each image's own normalised capture time (`FramePair.eval_camera_times`).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from drivingscene.data.frame_pair import FramePair
from drivingscene.errors import InputError


def _check(pair: FramePair) -> np.ndarray:
    if pair.num_eval == 0:
        raise InputError("the scene has no intermediate frames (eval_images) to predict")
    return pair.eval_camera_times()  # [M, V]


def copy_nearest_frames(pair: FramePair) -> Tensor:
    """``[M, V, H, W, 3]`` float in [0, 1]: the same camera's keyframe image nearest in time."""
    times = _check(pair)
    keyframe = (times > 0.5).astype(np.int64)  # [M, V]
    views = np.arange(pair.num_views)[None].repeat(len(times), 0)
    return torch.from_numpy(pair.images[keyframe, views]).float() / 255.0


def blend_frames(pair: FramePair) -> Tensor:
    """``[M, V, H, W, 3]`` float in [0, 1]: the two keyframe images blended by time."""
    t = torch.from_numpy(np.clip(_check(pair), 0.0, 1.0)).float()[..., None, None, None]  # [M, V, 1, 1, 1]
    images = torch.from_numpy(pair.images).float() / 255.0  # [2, V, H, W, 3]
    return (1 - t) * images[0] + t * images[1]
