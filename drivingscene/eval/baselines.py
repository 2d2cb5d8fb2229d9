"""Trivial baselines: what a method must beat.

For the in-between frame, with no geometry:

- copy the nearest keyframe: each camera's eval image predicted by that camera's keyframe image
  nearest in time (t <= 0.5: keyframe 0);
- blend the two keyframes: (1 - t) I_0 + t I_1 per pixel.

t is each image's own normalised capture time (`FramePair.eval_camera_times`).

For depth against LiDAR:

- the road plane: every ray meets the ego frame's z = 0 plane (the road under the car in nuScenes
  and DDAD) or, at and above the horizon, the far limit; no image is looked at;
- the nearest LiDAR return: each held-out return predicted by the nearest return that was kept
  (`nearest_return_depth`), a reference for how far any dense depth map at this resolution can
  agree with returns it did not see (depth edges, leaves, thin poles).
"""

from __future__ import annotations

import cv2
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


def nearest_return_depth(kept: np.ndarray) -> np.ndarray:
    """``[..., H, W]`` float32: at every pixel the depth of the nearest (Euclidean, in pixels)
    non-zero return of ``kept`` ``[..., H, W]``; 0 in images with no return at all."""
    flat = kept.reshape(-1, *kept.shape[-2:])
    out = np.zeros_like(flat, dtype=np.float32)
    for i, image in enumerate(flat):
        has = image > 0
        if not has.any():
            continue
        # labels of the nearest zero pixel of the input: the returns are its zeros
        _, labels = cv2.distanceTransformWithLabels(
            (~has).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE, labelType=cv2.DIST_LABEL_PIXEL
        )
        values = np.zeros(labels.max() + 1, np.float32)
        values[labels[has]] = image[has]
        out[i] = values[labels]
    return out.reshape(kept.shape)
