"""Small valid frame pairs built in memory (no GL, no files), for tests."""

from __future__ import annotations

import numpy as np

from drivingscene.data import FramePair


def make_rig(num_views: int = 3, height: int = 12, width: int = 16) -> tuple[np.ndarray, np.ndarray]:
    """Intrinsics [V, 3, 3] and cam_to_ego [V, 4, 4] of cameras spread in yaw around a z-up ego."""
    intrinsics = np.tile(
        np.array([[width * 0.8, 0, (width - 1) / 2], [0, width * 0.8, (height - 1) / 2], [0, 0, 1]], np.float32),
        (num_views, 1, 1),
    )
    cam_to_ego = np.zeros((num_views, 4, 4), np.float32)
    for i, yaw in enumerate(np.linspace(0, 2 * np.pi, num_views, endpoint=False)):
        forward = np.array([np.cos(yaw), np.sin(yaw), 0.0])
        right = np.array([np.sin(yaw), -np.cos(yaw), 0.0])
        down = np.array([0.0, 0.0, -1.0])
        cam_to_ego[i, :3, :3] = np.stack([right, down, forward], axis=1)
        cam_to_ego[i, :3, 3] = [1.0 + 0.5 * np.cos(yaw), 0.5 * np.sin(yaw), 1.5]
        cam_to_ego[i, 3, 3] = 1
    return intrinsics, cam_to_ego


def make_pair(num_views: int = 3, height: int = 12, width: int = 16, *, with_gt: bool = True, seed: int = 0) -> FramePair:
    rng = np.random.default_rng(seed)
    intrinsics, cam_to_ego = make_rig(num_views, height, width)
    ego_to_world = np.tile(np.eye(4), (2, 1, 1))
    ego_to_world[:, :3, 3] = [[10.0, -3.0, 0.0], [14.0, -3.0, 0.0]]
    shape = (2, num_views, height, width)
    gt = {}
    if with_gt:
        gt = dict(
            gt_depth=rng.uniform(1, 50, shape).astype(np.float32),
            gt_flow=rng.normal(size=shape + (2,)).astype(np.float32),
            gt_scene_flow=rng.normal(size=shape + (3,)).astype(np.float32),
            gt_dynamic=rng.uniform(size=shape) < 0.1,
            eval_images=rng.integers(0, 255, (1, num_views, height, width, 3), dtype=np.uint8),
            eval_timestamps=np.array([100.25]),
            eval_ego_to_world=ego_to_world[:1].copy(),
        )
    return FramePair(
        images=rng.integers(0, 255, (2, num_views, height, width, 3), dtype=np.uint8),
        intrinsics=intrinsics,
        cam_to_ego=cam_to_ego,
        ego_to_world=ego_to_world,
        timestamps=np.array([100.0, 100.5]),
        camera_names=tuple(f"CAM_{i}" for i in range(num_views)),
        **gt,
    )
