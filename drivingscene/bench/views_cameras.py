"""The viewpoints of ``drivingscene bench views``: where a viewer's user looks from.

Every class but the overview starts from each rig camera at normalised time t, posed as the viewer
poses it (`Reconstruction.cam_to_world_at`: the ego pose interpolated between the keyframes, then
``cam_to_ego``), with the rig's intrinsics and the input size:

- ``rig``: the rig pose itself (the reference class; at t = 0 the input views),
- ``side 1 m`` / ``side 2 m``: the camera moved along the ego's lateral axis (ego y, left), both ways
  (+y and -y) for every camera,
- ``up 2 m``: moved up along the ego's z axis,
- ``up 10 m, 45° down``: moved 10 m up and pitched 45 degrees down about its own x axis,
- ``overview``: the viewer's default chase view (`drivingscene_view.camera.CameraController.reset`,
  replicated here: the bench does not import the viewer), one camera,
- magnification k: the rig pose at k times the input size, intrinsics scaled so that the pixel grid
  refines in place (`synth.rig.scale_intrinsics_np`: f' = k f, c' = (c + 0.5) k - 0.5).

Poses are ``cam_to_world`` ``[B, 4, 4]`` float64 in OpenCV camera axes (x right, y down, z forward);
the ego frame is x forward, y left, z up; metres.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from drivingscene.geometry.se3 import interpolate_pose
from drivingscene.synth.rig import scale_intrinsics_np

RIG, SIDE_1, SIDE_2, UP_2, UP_10_DOWN, OVERVIEW = "rig", "side 1 m", "side 2 m", "up 2 m", "up 10 m, 45° down", "overview"
CLASSES = (RIG, SIDE_1, SIDE_2, UP_2, UP_10_DOWN, OVERVIEW)
MOVES = {
    SIDE_1: (0.0, 1.0, 0.0),
    SIDE_2: (0.0, 2.0, 0.0),
    UP_2: (0.0, 0.0, 2.0),
    UP_10_DOWN: (0.0, 0.0, 10.0),
}  # ego axes, metres
DOWN_PITCH_DEG = 45.0
# The viewer's default overview (app/camera.py, CameraController.reset and NavCamera)
OVERVIEW_PITCH = -0.45  # radians, negative looks down
OVERVIEW_DISTANCE = 28.0  # metres from the eye to the target
OVERVIEW_AHEAD = 10.0  # metres: the target is this far ahead of the ego, at its height
OVERVIEW_FOV_Y = 60.0  # degrees


@dataclass(frozen=True, eq=False)
class Viewpoints:
    """The cameras of one viewpoint class at one time."""

    name: str  # class (CLASSES)
    t: float  # normalised time
    magnification: int  # image size / input size (1 except magnified rig views)
    cams_to_world: np.ndarray  # [B, 4, 4] float64
    intrinsics: np.ndarray  # [B, 3, 3] float64, pixels
    size: tuple[int, int]  # (H, W)
    sources: np.ndarray  # [B] int: the rig camera each view derives from, -1 for the overview

    def __len__(self) -> int:
        return len(self.cams_to_world)

    @property
    def world_to_cam(self) -> np.ndarray:
        """``[B, 4, 4]`` float64."""
        return np.linalg.inv(self.cams_to_world)


def ego_pose_at(ego_to_world: np.ndarray, t: float) -> np.ndarray:
    """``[4, 4]`` float64 ego pose at normalised time t from the keyframe poses ``[2, 4, 4]``, by the
    SE(3) interpolation of `Reconstruction.ego_to_world_at` (what the viewer shows)."""
    poses = torch.from_numpy(np.asarray(ego_to_world, np.float64))
    return interpolate_pose(poses[0], poses[1], torch.tensor(float(t), dtype=torch.float64)).numpy()


def rig_poses(ego_to_world: np.ndarray, cam_to_ego: np.ndarray, t: float) -> np.ndarray:
    """``[V, 4, 4]`` float64 rig camera poses at normalised time t (`Reconstruction.cam_to_world_at`)."""
    return ego_pose_at(ego_to_world, t)[None] @ np.asarray(cam_to_ego, np.float64)


def moved(cams_to_world: np.ndarray, ego_to_world: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """Cameras ``[B, 4, 4]`` translated by ``offset`` ``[3]`` (metres, ego axes), orientation kept."""
    out = np.array(cams_to_world, np.float64, copy=True)
    out[:, :3, 3] += np.asarray(ego_to_world, np.float64)[:3, :3] @ np.asarray(offset, np.float64)
    return out


def pitched_down(cams_to_world: np.ndarray, degrees: float) -> np.ndarray:
    """Cameras ``[B, 4, 4]`` rotated about their own x axis so that the optical axis tilts ``degrees``
    towards the image's down direction (y); centres kept."""
    a = math.radians(degrees)
    c, s = math.cos(a), math.sin(a)
    # columns: the new camera axes in the old camera's: x' = x, y' = c y - s z, z' = s y + c z
    rot = np.array([[1.0, 0.0, 0.0], [0.0, c, s], [0.0, -s, c]])
    out = np.array(cams_to_world, np.float64, copy=True)
    out[:, :3, :3] = out[:, :3, :3] @ rot
    return out


def overview_camera(ego_to_world: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """The viewer's default chase view of an ego at ``ego_to_world`` ``[4, 4]``: ``(cam_to_world [4, 4],
    intrinsics [3, 3])`` for a ``width`` x ``height`` viewport, z-up world.

    As `CameraController.reset`: yaw of the ego's forward axis, pitch -0.45 rad, the target 10 m ahead
    of the ego (horizontally), the eye 28 m back from it along the view direction, no roll, a 60 degree
    vertical field of view with square pixels and the principal point at the image centre."""
    ego = np.asarray(ego_to_world, np.float64)
    yaw = math.atan2(ego[1, 0], ego[0, 0])
    cp = math.cos(OVERVIEW_PITCH)
    forward = np.array([cp * math.cos(yaw), cp * math.sin(yaw), math.sin(OVERVIEW_PITCH)])
    target = ego[:3, 3] + OVERVIEW_AHEAD * np.array([math.cos(yaw), math.sin(yaw), 0.0])
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    cam_to_world = np.eye(4)
    cam_to_world[:3, :3] = np.stack([right, down, forward], axis=1)
    cam_to_world[:3, 3] = target - OVERVIEW_DISTANCE * forward
    f = 0.5 * height / math.tan(math.radians(OVERVIEW_FOV_Y) / 2)
    intrinsics = np.array([[f, 0.0, (width - 1) / 2], [0.0, f, (height - 1) / 2], [0.0, 0.0, 1.0]])
    return cam_to_world, intrinsics


def viewpoint_class(
    name: str,
    t: float,
    ego_to_world: np.ndarray,  # [2, 4, 4] keyframe ego poses
    cam_to_ego: np.ndarray,  # [V, 4, 4]
    intrinsics: np.ndarray,  # [V, 3, 3]
    size: tuple[int, int],  # input (H, W)
    overview_size: tuple[int, int] = (720, 1280),  # (H, W)
) -> Viewpoints:
    """The cameras of class ``name`` at normalised time t."""
    ego = ego_pose_at(ego_to_world, t)
    rig = rig_poses(ego_to_world, cam_to_ego, t)
    views = len(rig)
    k = np.asarray(intrinsics, np.float64)
    sources = np.arange(views)
    if name == RIG:
        return Viewpoints(name, t, 1, rig, k, tuple(size), sources)
    if name == OVERVIEW:
        cam, k_over = overview_camera(ego, overview_size[1], overview_size[0])
        return Viewpoints(name, t, 1, cam[None], k_over[None], tuple(overview_size), np.array([-1]))
    if name not in MOVES:
        raise ValueError(f"viewpoint class: expected one of {', '.join(CLASSES)}, found {name!r}")
    offset = np.asarray(MOVES[name])
    if name in (SIDE_1, SIDE_2):  # both ways: +y (left) for every camera, then -y
        cams = np.concatenate([moved(rig, ego, offset), moved(rig, ego, -offset)])
        return Viewpoints(name, t, 1, cams, np.concatenate([k, k]), tuple(size), np.concatenate([sources, sources]))
    cams = moved(rig, ego, offset)
    if name == UP_10_DOWN:
        cams = pitched_down(cams, DOWN_PITCH_DEG)
    return Viewpoints(name, t, 1, cams, k, tuple(size), sources)


def magnified_rig(
    t: float, k: int, ego_to_world: np.ndarray, cam_to_ego: np.ndarray, intrinsics: np.ndarray, size: tuple[int, int]
) -> Viewpoints:
    """The rig cameras at normalised time t at ``k`` times the input ``size`` (H, W)."""
    rig = rig_poses(ego_to_world, cam_to_ego, t)
    big = (int(size[0]) * k, int(size[1]) * k)
    return Viewpoints(RIG, t, k, rig, scale_intrinsics_np(intrinsics, k), big, np.arange(len(rig)))
