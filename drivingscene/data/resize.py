"""A frame pair at another image size (what a method reads when it runs at a lower resolution)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np


def resized_pair(pair, scale: float):
    """The pair's keyframes at ``scale`` of their size (what the model reads), without ground truth
    or eval frames."""
    import cv2
    import torch

    from drivingscene.geometry.camera import scale_intrinsics

    height, width = pair.image_size
    h, w = max(8, round(height * scale)), max(8, round(width * scale))
    images = np.stack([[cv2.resize(im, (w, h), interpolation=cv2.INTER_AREA) for im in frame] for frame in pair.images])
    k = scale_intrinsics(torch.from_numpy(pair.intrinsics), w / width, h / height).numpy()
    mask = None
    if pair.valid_mask is not None:
        mask = np.stack([cv2.resize(m.astype(np.uint8), (w, h), interpolation=cv2.INTER_NEAREST) > 0 for m in pair.valid_mask])
    empty = dict.fromkeys(
        (
            "gt_depth",
            "gt_flow",
            "gt_scene_flow",
            "gt_dynamic",
            "eval_images",
            "eval_timestamps",
            "eval_ego_to_world",
            "eval_dynamic",
            "eval_camera_ego_to_world",
            "eval_camera_timestamps",
        )
    )
    return replace(pair, images=images, intrinsics=k, valid_mask=mask, **empty)
