"""A tiny dataset in nuScenes layout (JSON tables + images + LiDAR .pcd.bin) written from a frame
pair, for reading back through nuscenes-devkit without the real dataset.

One scene of two samples (the pair's keyframes, at the LiDAR's times and poses), the pair's eval
frame as one camera sweep between them, and each camera captured at its own time and ego pose, around
the LiDAR's time (as nuScenes cameras fire when the LiDAR sweeps past them). LiDAR: the
pixels of ``gt_depth`` (every ``stride``-th), unprojected with the written poses, so that
projecting them back lands on the same pixels at the same depth.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

from drivingscene.geometry.se3 import matrix_to_quat

VERSION = "v1.0-mini"
SCENE = "scene-0001"
CAMERA_DELAY_S = 0.008  # camera i fires (i - 2.5) * 8 ms after its frame's time: their mean is the frame's
LIDAR_TO_EGO = np.array([[0.0, 1.0, 0.0, 0.9], [-1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 1.8], [0.0, 0.0, 0.0, 1.0]])


def _quat(mat: np.ndarray) -> list[float]:
    import torch

    return [float(v) for v in matrix_to_quat(torch.from_numpy(np.ascontiguousarray(mat[:3, :3])))]


def _pose_fields(mat: np.ndarray) -> dict:
    return {"rotation": _quat(mat), "translation": [float(v) for v in mat[:3, 3]]}


def camera_poses(pair) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per-image times and ego poses ``[F, V]`` / ``[F, V, 4, 4]`` of the written frames
    (keyframe 0, the eval frame, keyframe 1), and the frames' own times and poses."""
    times = np.array([pair.timestamps[0], pair.eval_timestamps[0], pair.timestamps[1]])
    egos = np.stack([pair.ego_to_world[0], pair.eval_ego_to_world[0], pair.ego_to_world[1]])
    delays = CAMERA_DELAY_S * (np.arange(pair.num_views) - (pair.num_views - 1) / 2)
    cam_times = times[:, None] + delays[None]
    speed = (pair.ego_to_world[1, :3, 3] - pair.ego_to_world[0, :3, 3]) / pair.duration
    cam_egos = np.repeat(egos[:, None], pair.num_views, axis=1).copy()
    cam_egos[..., :3, 3] += delays[None, :, None] * speed  # the ego kept moving while the cameras fired
    return cam_times, cam_egos, times, egos


def _lidar_points(pair, k: int, cam_egos: np.ndarray, lidar_to_world: np.ndarray, stride: int) -> np.ndarray:
    """``[N, 5]`` float32 (x y z intensity ring) in the LiDAR frame from gt_depth at keyframe k."""
    pts = []
    height, width = pair.image_size
    v, u = np.mgrid[0:height:stride, 0:width:stride]
    for view in range(pair.num_views):
        depth = pair.gt_depth[k, view][v, u]
        keep = (depth > 0.5) & (depth < 70)
        kinv = np.linalg.inv(pair.intrinsics[view].astype(np.float64))
        rays = np.stack([u[keep], v[keep], np.ones(keep.sum())], -1) @ kinv.T
        cam = rays * depth[keep][:, None]
        cam_to_world = cam_egos[view] @ pair.cam_to_ego[view].astype(np.float64)
        pts.append(cam @ cam_to_world[:3, :3].T + cam_to_world[:3, 3])
    world = np.concatenate(pts)
    to_lidar = np.linalg.inv(lidar_to_world)
    local = world @ to_lidar[:3, :3].T + to_lidar[:3, 3]
    return np.concatenate([local, np.zeros((len(local), 2))], 1).astype(np.float32)


def write_nuscenes(pair, root: Path, stride: int = 3) -> Path:
    """Write ``pair`` (with gt_depth and one eval frame) as a nuScenes dataset under ``root``."""
    root = Path(root)
    tables: dict[str, list] = {
        k: []
        for k in (
            "category",
            "attribute",
            "visibility",
            "instance",
            "sensor",
            "calibrated_sensor",
            "ego_pose",
            "log",
            "scene",
            "sample",
            "sample_data",
            "sample_annotation",
            "map",
        )
    }
    tables["log"].append({"token": "log0", "logfile": "log0", "vehicle": "v", "date_captured": "2026-11-24", "location": "here"})
    tables["map"].append({"token": "map0", "filename": "maps/map0.png", "category": "semantic_prior", "log_tokens": ["log0"]})
    cam_times, cam_egos, times, egos = camera_poses(pair)
    us = lambda s: int(round(s * 1e6))  # noqa: E731
    sample_tokens = ["sample0", "sample1"]
    for k, token in enumerate(sample_tokens):
        tables["sample"].append(
            {
                "token": token,
                "timestamp": us(times[2 * k]),
                "scene_token": "scene0",
                "prev": sample_tokens[k - 1] if k else "",
                "next": "" if k else sample_tokens[1],
            }
        )
    tables["scene"].append(
        {
            "token": "scene0",
            "name": SCENE,
            "description": "",
            "log_token": "log0",
            "nbr_samples": 2,
            "first_sample_token": "sample0",
            "last_sample_token": "sample1",
        }
    )
    channels = list(pair.camera_names) + ["LIDAR_TOP"]
    for i, channel in enumerate(channels):
        lidar = channel == "LIDAR_TOP"
        tables["sensor"].append({"token": f"sensor{i}", "channel": channel, "modality": "lidar" if lidar else "camera"})
        calib = LIDAR_TO_EGO if lidar else pair.cam_to_ego[i].astype(np.float64)
        tables["calibrated_sensor"].append(
            {
                "token": f"cs{i}",
                "sensor_token": f"sensor{i}",
                **_pose_fields(calib),
                "camera_intrinsic": [] if lidar else pair.intrinsics[i].astype(float).tolist(),
            }
        )
        frames = (0, 2) if lidar else (0, 1, 2)
        tokens = [f"sd_{channel}_{f}" for f in frames]
        for n, (f, token) in enumerate(zip(frames, tokens)):
            key = f != 1
            folder = "samples" if key else "sweeps"
            name = f"{folder}/{channel}/{channel}_{f}." + ("pcd.bin" if lidar else "jpg")
            (root / name).parent.mkdir(parents=True, exist_ok=True)
            t = times[f] if lidar else cam_times[f, i]
            ego = egos[f] if lidar else cam_egos[f, i]
            if lidar:
                _lidar_points(pair, f // 2, cam_egos[f], ego @ LIDAR_TO_EGO, stride).tofile(root / name)
            else:
                image = pair.images[f // 2, i] if key else pair.eval_images[0, i]
                cv2.imwrite(str(root / name) + ".png", image[..., ::-1])  # lossless PNG content ...
                (root / (name + ".png")).rename(root / name)  # ... under nuScenes' .jpg name
            tables["ego_pose"].append({"token": f"ego_{token}", "timestamp": us(t), **_pose_fields(ego)})
            tables["sample_data"].append(
                {
                    "token": token,
                    "sample_token": sample_tokens[min(f, 1) if key else 1],
                    "ego_pose_token": f"ego_{token}",
                    "calibrated_sensor_token": f"cs{i}",
                    "timestamp": us(t),
                    "fileformat": "pcd" if lidar else "jpg",
                    "is_key_frame": key,
                    "height": 0 if lidar else pair.image_size[0],
                    "width": 0 if lidar else pair.image_size[1],
                    "filename": name,
                    "prev": tokens[n - 1] if n else "",
                    "next": tokens[n + 1] if n + 1 < len(tokens) else "",
                }
            )
    (root / VERSION).mkdir(parents=True, exist_ok=True)
    (root / "maps").mkdir(exist_ok=True)
    cv2.imwrite(str(root / "maps" / "map0.png"), np.zeros((4, 4), np.uint8))  # the devkit checks it exists
    for name, rows in tables.items():
        (root / VERSION / f"{name}.json").write_text(json.dumps(rows))
    return root
