"""The nuScenes-like camera rig: six cameras around a z-up, x-forward ego.

Mounting positions, yaws and focal lengths follow nuScenes' calibration (rounded). Intrinsics are
the 1600x900 nuScenes focal lengths scaled to the output size, ``fx = f * W / 1600`` and
``fy = f * H / 900`` (so pixels are slightly non-square when H / W != 9 / 16), with the principal
point at the image centre ``((W - 1) / 2, (H - 1) / 2)`` under the integer-pixel-centre convention.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# name: (x, y, z mount in the ego frame in metres, yaw in degrees, focal length in px at 1600x900)
RIG_SPEC: dict[str, tuple[float, float, float, float, float]] = {
    "CAM_FRONT": (1.70, 0.00, 1.51, 0.0, 1266.4),
    "CAM_FRONT_RIGHT": (1.55, -0.49, 1.50, -55.0, 1260.8),
    "CAM_BACK_RIGHT": (1.05, -0.48, 1.56, -110.0, 1259.5),
    "CAM_BACK": (0.05, 0.00, 1.59, 180.0, 809.2),
    "CAM_BACK_LEFT": (1.05, 0.48, 1.56, 110.0, 1256.7),
    "CAM_FRONT_LEFT": (1.52, 0.49, 1.51, 55.0, 1272.6),
}
CAMERA_NAMES: tuple[str, ...] = tuple(RIG_SPEC)
NUSCENES_SIZE = (900, 1600)  # (H, W) the focal lengths refer to


@dataclass(frozen=True, eq=False)
class Rig:
    camera_names: tuple[str, ...]  # [V]
    intrinsics: np.ndarray  # [V, 3, 3] float64, pixels
    cam_to_ego: np.ndarray  # [V, 4, 4] float64, OpenCV camera axes
    height: int
    width: int


def yaw_camera_to_ego(x: float, y: float, z: float, yaw_deg: float) -> np.ndarray:
    """``[4, 4]`` camera-to-ego for a level camera looking along ``yaw`` (0 = ego forward, + = left)."""
    yaw = np.radians(yaw_deg)
    forward = np.array([np.cos(yaw), np.sin(yaw), 0.0])
    right = np.array([np.sin(yaw), -np.cos(yaw), 0.0])
    down = np.array([0.0, 0.0, -1.0])
    out = np.eye(4)
    out[:3, :3] = np.stack([right, down, forward], axis=1)  # columns: camera x, y, z in ego axes
    out[:3, 3] = (x, y, z)
    return out


def nuscenes_intrinsics(focal: float, height: int, width: int) -> np.ndarray:
    """``[3, 3]`` pinhole intrinsics for an H x W image of a nuScenes camera with this focal length."""
    return np.array(
        [
            [focal * width / NUSCENES_SIZE[1], 0.0, (width - 1) / 2],
            [0.0, focal * height / NUSCENES_SIZE[0], (height - 1) / 2],
            [0.0, 0.0, 1.0],
        ]
    )


def make_rig(height: int, width: int) -> Rig:
    """The six-camera rig for ``height x width`` images."""
    intrinsics = np.stack([nuscenes_intrinsics(spec[4], height, width) for spec in RIG_SPEC.values()])
    cam_to_ego = np.stack([yaw_camera_to_ego(*spec[:4]) for spec in RIG_SPEC.values()])
    return Rig(CAMERA_NAMES, intrinsics, cam_to_ego, height, width)


def scale_intrinsics_np(intrinsics: np.ndarray, scale: float) -> np.ndarray:
    """Intrinsics ``[..., 3, 3]`` for an image ``scale`` times larger (same rule as
    ``drivingscene.geometry.scale_intrinsics``: c' = (c + 0.5) * s - 0.5)."""
    out = np.array(intrinsics, dtype=np.float64, copy=True)
    out[..., 0, 0] *= scale
    out[..., 0, 1] *= scale
    out[..., 1, 1] *= scale
    out[..., 0, 2] = (intrinsics[..., 0, 2] + 0.5) * scale - 0.5
    out[..., 1, 2] = (intrinsics[..., 1, 2] + 0.5) * scale - 0.5
    return out
