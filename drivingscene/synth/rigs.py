"""Rigs beyond the fixed nuScenes one: DDAD's six cameras, and random rigs of 5-8 cameras per seed.

A model trained on one rig learns its focal lengths, mounting heights and yaws; these rigs vary all
of them. The output image size is always the config's: fields of view vary through the intrinsics
(square pixels, ``fx = fy = (W / 2) / tan(hfov / 2)``). Cameras are ordered around the car as in
nuScenes and DDAD: the front camera first, then clockwise seen from above (decreasing yaw).
"""

from __future__ import annotations

import numpy as np

from drivingscene.synth.rig import CAMERA_NAMES, Rig, make_rig, yaw_camera_to_ego
from drivingscene.synth.streams import stream

RIG_KINDS = ("nuscenes", "ddad", "random")
RANDOM_VIEWS = (5, 8)  # fewest and most cameras of a random rig

# DDAD's rig from its calibration (rounded): name: (x, y, z mount in metres, yaw, pitch, roll in
# degrees, horizontal field of view in degrees). Undistorted 1936x1216 images, square pixels.
DDAD_SPEC: dict[str, tuple[float, float, float, float, float, float, float]] = {
    "CAMERA_01": (1.49, 0.29, 1.56, 3.9, -0.5, -0.3, 48.0),
    "CAMERA_06": (1.53, -0.41, 1.53, -53.1, 0.4, 0.2, 85.0),
    "CAMERA_08": (1.10, -0.46, 1.55, -124.5, 0.0, -0.2, 85.0),
    "CAMERA_09": (0.15, 0.13, 1.53, -179.0, 1.2, 0.8, 85.0),
    "CAMERA_07": (1.10, 0.43, 1.56, 123.7, -1.0, 0.5, 85.0),
    "CAMERA_05": (1.52, 0.46, 1.58, 51.7, -1.0, -0.7, 85.0),
}


def camera_to_ego(x: float, y: float, z: float, yaw_deg: float, pitch_deg: float = 0.0, roll_deg: float = 0.0) -> np.ndarray:
    """``[4, 4]`` camera-to-ego of a camera looking along ``yaw`` (0 = ego forward, + = left), tilted
    up by ``pitch`` (about its x axis) and rolled by ``roll`` about its optical axis (+ = its x axis
    tilts down: clockwise seen from behind the camera)."""
    out = yaw_camera_to_ego(x, y, z, yaw_deg)
    p, r = np.radians(pitch_deg), np.radians(roll_deg)
    tilt = np.array([[1.0, 0.0, 0.0], [0.0, np.cos(p), -np.sin(p)], [0.0, np.sin(p), np.cos(p)]])  # z -> (0, -sin p, cos p): up
    roll = np.array([[np.cos(r), -np.sin(r), 0.0], [np.sin(r), np.cos(r), 0.0], [0.0, 0.0, 1.0]])
    out[:3, :3] = out[:3, :3] @ tilt @ roll
    return out


def pinhole_intrinsics(hfov_deg: float, height: int, width: int, dx: float = 0.0, dy: float = 0.0) -> np.ndarray:
    """``[3, 3]`` square-pixel intrinsics with horizontal field of view ``hfov``; the principal point
    is the image centre ``((W - 1) / 2, (H - 1) / 2)`` moved by (dx, dy) pixels."""
    f = (width / 2) / np.tan(np.radians(hfov_deg) / 2)
    return np.array([[f, 0.0, (width - 1) / 2 + dx], [0.0, f, (height - 1) / 2 + dy], [0.0, 0.0, 1.0]])


def make_ddad_rig(height: int, width: int) -> Rig:
    """DDAD's six cameras (front 48 degrees, five wide 85 degrees) for ``height x width`` images."""
    intrinsics = np.stack([pinhole_intrinsics(s[6], height, width) for s in DDAD_SPEC.values()])
    cam_to_ego = np.stack([camera_to_ego(*s[:6]) for s in DDAD_SPEC.values()])
    return Rig(tuple(DDAD_SPEC), intrinsics, cam_to_ego, height, width)


def _random_yaws(rng: np.random.Generator, views: int) -> np.ndarray:
    """``[V]`` degrees: the front camera at 0 +- 5, the rest spread clockwise with jitter."""
    spacing = 360.0 / views
    yaws = -spacing * np.arange(views) + rng.uniform(-0.22, 0.22, views) * spacing
    yaws[0] = rng.uniform(-5.0, 5.0)
    return (yaws + 180.0) % 360.0 - 180.0


def _random_fovs(rng: np.random.Generator, yaws: np.ndarray) -> np.ndarray:
    """``[V]`` horizontal fields of view: front 40-75 degrees; others around a per-rig base between
    nuScenes-like (~65) and DDAD-like (~85) or wider, sometimes a very wide back camera."""
    base = rng.uniform(60.0, 110.0)
    fovs = np.clip(base + rng.normal(0.0, 7.0, len(yaws)), 60.0, 120.0)
    fovs[0] = rng.uniform(40.0, 75.0)
    back = int(np.argmax(np.abs(yaws)))
    if back != 0 and rng.uniform() < 0.35:
        fovs[back] = rng.uniform(95.0, 120.0)  # nuScenes' back camera is ~110 degrees
    return fovs


def _random_mounts(rng: np.random.Generator, yaws: np.ndarray) -> np.ndarray:
    """``[V, 3]`` mounts on the roof, on an ellipse around a roof centre in each camera's direction."""
    views = len(yaws)
    centre_x, half_x, half_y = rng.uniform(0.6, 1.3), rng.uniform(0.5, 0.9), rng.uniform(0.3, 0.55)
    height = rng.uniform(1.3, 2.1)
    rad = np.radians(yaws)
    reach = rng.uniform(0.75, 1.0, views)
    x = centre_x + half_x * np.cos(rad) * reach + rng.uniform(-0.08, 0.08, views)
    y = half_y * np.sin(rad) * reach + rng.uniform(-0.08, 0.08, views)
    z = height + rng.uniform(-0.06, 0.06, views)
    return np.stack([x, y, z], -1)


def sample_random_rig(rng: np.random.Generator, height: int, width: int) -> Rig:
    """A rig of 5-8 cameras: yaws, fields of view, mounts, pitch (-8..5 degrees), roll (+-2) and
    principal points (+-3 % of the image) all drawn from ``rng``. Names CAM_0 (front) ... clockwise."""
    views = int(rng.integers(RANDOM_VIEWS[0], RANDOM_VIEWS[1] + 1))
    yaws = _random_yaws(rng, views)
    fovs = _random_fovs(rng, yaws)
    mounts = _random_mounts(rng, yaws)
    pitches = np.clip(rng.uniform(-4.0, 2.0) + rng.uniform(-3.0, 3.0, views), -8.0, 5.0)
    rolls = rng.uniform(-2.0, 2.0, views)
    shifts = rng.uniform(-0.03, 0.03, (views, 2)) * [width, height]
    intrinsics = np.stack([pinhole_intrinsics(f, height, width, *d) for f, d in zip(fovs, shifts)])
    cam_to_ego = np.stack([camera_to_ego(*m, y, p, r) for m, y, p, r in zip(mounts, yaws, pitches, rolls)])
    return Rig(tuple(f"CAM_{i}" for i in range(views)), intrinsics, cam_to_ego, height, width)


def make_rig_of_kind(kind: str, height: int, width: int, seed: int) -> Rig:
    """The rig of ``kind`` (one of ``RIG_KINDS``) for this seed."""
    if kind == "ddad":
        return make_ddad_rig(height, width)
    if kind == "random":
        return sample_random_rig(stream(seed, "rig"), height, width)
    return make_rig(height, width)


def guaranteed_camera_names(kind: str) -> tuple[str, ...]:
    """Camera names that every rig of ``kind`` has, whatever the seed (empty for an unknown kind)."""
    if kind == "nuscenes":
        return CAMERA_NAMES
    if kind == "ddad":
        return tuple(DDAD_SPEC)
    if kind == "random":
        return tuple(f"CAM_{i}" for i in range(RANDOM_VIEWS[0]))
    return ()


def camera_index(names: tuple[str, ...], camera: str) -> int:
    """Index of ``camera`` given as a name of ``names`` or as a decimal index."""
    return names.index(camera) if camera in names else int(camera)


def camera_yaws(cam_to_ego: np.ndarray) -> np.ndarray:
    """``[V]`` degrees: where each camera's optical axis points in the ego's ground plane (+ = left)."""
    forward = np.asarray(cam_to_ego)[:, :3, 2]
    return np.degrees(np.arctan2(forward[:, 1], forward[:, 0]))
