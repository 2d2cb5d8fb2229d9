"""A frame pair written as a rig folder (``rig.json``, PNG images, mask PNGs, LiDAR .npy): the
inverse of `rig.import_rig`, for tests and for editing a scene's files by hand.

Frames are written in time order: keyframe 0, the eval frames, keyframe 1, so the pair comes back
with ``import_rig(folder, (0, M + 1), tuple(range(1, M + 1)))``. ``gt_depth`` becomes LiDAR points
(every pixel with depth > 0 unprojected into its frame's ego frame); where the cameras overlap a
point can land in another camera too, so depth comes back exactly only for rigs without overlap.
``gt_flow``, ``gt_scene_flow`` and the dynamic masks have no place in a rig folder and are dropped.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import cv2
import numpy as np

from drivingscene.data.atomic import atomic_folder, atomic_path, atomic_write_text
from drivingscene.data.frame_pair import FramePair
from drivingscene.data.importers.rig_schema import RIG_FILE, RIG_FORMAT, RIG_VERSION
from drivingscene.errors import OutputError


def _file_stem(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]", "_", name)


def _write_png(path: Path, image: np.ndarray) -> str:
    """Write uint8 ``[H, W, 3]`` RGB or ``[H, W]`` grey; returns the name relative to the folder."""
    pixels = image[..., ::-1] if image.ndim == 3 else image
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), np.ascontiguousarray(pixels)):
            raise OutputError(f"{path}: could not write the PNG")
    return f"{path.parent.name}/{path.name}"


def _lidar_points(
    depth: np.ndarray,  # [V, H, W] z-depth, 0 = unknown
    intrinsics: np.ndarray,  # [V, 3, 3]
    cam_to_ego: np.ndarray,  # [V, 4, 4]
    camera_ego_to_world: np.ndarray,  # [V, 4, 4] ego pose at each image's capture
    ego_to_world: np.ndarray,  # [4, 4] the frame's ego pose
) -> np.ndarray:
    """``[N, 3]`` float64 points in the frame's ego frame: every pixel with depth, unprojected."""
    world_to_frame = np.linalg.inv(ego_to_world)
    out = []
    for v in range(depth.shape[0]):
        rows, cols = np.nonzero(depth[v] > 0)
        z = depth[v][rows, cols].astype(np.float64)
        rays = (
            np.stack([cols, rows, np.ones_like(cols)], axis=1).astype(np.float64)
            @ np.linalg.inv(intrinsics[v].astype(np.float64)).T
        )
        cam = rays * z[:, None]
        to_frame = world_to_frame @ camera_ego_to_world[v] @ cam_to_ego[v].astype(np.float64)
        out.append(cam @ to_frame[:3, :3].T + to_frame[:3, 3])
    return np.concatenate(out)


def _cameras(pair: FramePair, folder: Path) -> list[dict]:
    cameras = []
    for v, name in enumerate(pair.camera_names):
        height, width = pair.image_size
        cam = {
            "name": name,
            "width": width,
            "height": height,
            "K": pair.intrinsics[v].astype(np.float64).tolist(),
            "cam_to_ego": pair.cam_to_ego[v].astype(np.float64).tolist(),
        }
        if pair.valid_mask is not None and not pair.valid_mask[v].all():
            mask = np.where(pair.valid_mask[v], 255, 0).astype(np.uint8)
            cam["mask"] = _write_png(folder / "masks" / f"{v:02d}_{_file_stem(name)}.png", mask)
        cameras.append(cam)
    return cameras


def _frames(pair: FramePair) -> list[tuple]:
    """Per frame in time order: (timestamp, ego_to_world, images [V, H, W, 3], camera times [V] or
    None, camera poses [V, 4, 4] or None, depth [V, H, W] or None)."""
    per_camera = pair.camera_timestamps is not None or pair.camera_ego_to_world is not None
    eval_per_camera = pair.eval_camera_timestamps is not None or pair.eval_camera_ego_to_world is not None
    keys = [
        (
            pair.timestamps[k],
            pair.ego_to_world[k],
            pair.images[k],
            pair.camera_timestamps[k] if pair.camera_timestamps is not None else None,
            pair.camera_ego_poses()[k] if per_camera else None,
            None if pair.gt_depth is None else pair.gt_depth[k],
        )
        for k in range(2)
    ]
    evals = [
        (
            pair.eval_timestamps[m],
            pair.eval_ego_to_world[m],
            pair.eval_images[m],
            pair.eval_camera_timestamps[m] if pair.eval_camera_timestamps is not None else None,
            pair.eval_camera_ego_poses()[m] if eval_per_camera else None,
            None,
        )
        for m in range(pair.num_eval)
    ]
    return [keys[0], *evals, keys[1]]


def export_rig(pair: FramePair, folder: str | Path) -> Path:
    """Write ``pair`` as a rig folder; returns the path of its ``rig.json``. ``folder`` must be new
    or empty; the rig is written beside it and renamed into place whole (`atomic_folder`), so a
    killed export leaves no folder of that name or a complete rig."""
    target = Path(folder)
    with atomic_folder(target) as staging:
        _write_rig(pair, staging)
    return target / RIG_FILE


def _write_rig(pair: FramePair, folder: Path) -> None:
    frames = []
    for f, (seconds, ego_to_world, images, cam_times, cam_poses, depth) in enumerate(_frames(pair)):
        frame = {"timestamp": float(seconds), "ego_to_world": np.asarray(ego_to_world, np.float64).tolist(), "images": {}}
        for v, name in enumerate(pair.camera_names):
            frame["images"][name] = _write_png(folder / "images" / f"{f:06d}_{v:02d}_{_file_stem(name)}.png", images[v])
        if cam_times is not None:
            frame["camera_timestamps"] = {n: float(t) for n, t in zip(pair.camera_names, cam_times)}
        if cam_poses is not None:
            frame["camera_ego_to_world"] = {n: np.asarray(p, np.float64).tolist() for n, p in zip(pair.camera_names, cam_poses)}
        if depth is not None:
            poses = cam_poses if cam_poses is not None else np.broadcast_to(ego_to_world, (pair.num_views, 4, 4))
            points = _lidar_points(depth, pair.intrinsics, pair.cam_to_ego, poses, ego_to_world)
            with atomic_path(folder / "lidar" / f"{f:06d}.npy") as tmp:
                np.save(tmp, points)
            frame["lidar"] = f"lidar/{f:06d}.npy"
        frames.append(frame)
    rig = {"format": RIG_FORMAT, "version": RIG_VERSION, "cameras": _cameras(pair, folder), "frames": frames}
    atomic_write_text(folder / RIG_FILE, json.dumps(rig, indent=1) + "\n")
