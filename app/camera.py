"""Viewer cameras in the library's conventions: OpenCV axes (x right, y down, z forward), ``world_to_cam``
4x4 float64, pinhole intrinsics with pixel centres at integer coordinates, z-up world.

``ViewCamera`` is what gets rendered; ``NavCamera`` is the interactive orbit/fly camera (no roll: its
x axis stays horizontal); ``rig_camera`` snaps to a rig camera at time t with the rig's exact K.
Follow-ego mode is a ``NavCamera`` whose frame is the ego pose at t instead of the world.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

Z_UP = np.eye(3)
# COLMAP / OpenCV-world PLYs from other tools: -y is up. Columns: where nav x, y, z go in the world.
Y_DOWN_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
UP_ROTATIONS = {"z": Z_UP, "-y": Y_DOWN_UP}  # keyed by ``Source.up`` (drivingscene.export.ply.ply_up_axis)


def up_rotation(up: str) -> np.ndarray:
    """``NavCamera.up_to_world`` ``[3, 3]`` for a world whose up axis is ``up`` ("z" or "-y")."""
    if up not in UP_ROTATIONS:
        raise ValueError(f"up axis: expected one of {', '.join(UP_ROTATIONS)}, found {up!r}")
    return UP_ROTATIONS[up].copy()


def invert_rigid(m: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = m[:3, :3].T
    out[:3, 3] = -m[:3, :3].T @ m[:3, 3]
    return out


def intrinsics_from_fov(width: int, height: int, fov_y_deg: float) -> np.ndarray:
    """K ``[3, 3]`` with square pixels, the principal point at the image centre ((W-1)/2, (H-1)/2)."""
    f = 0.5 * height / math.tan(math.radians(fov_y_deg) / 2)
    return np.array([[f, 0.0, (width - 1) / 2], [0.0, f, (height - 1) / 2], [0.0, 0.0, 1.0]])


def scale_intrinsics(k: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """K for an image resized by (sx, sy): pixel edges scale, so ``u' + 0.5 = sx (u + 0.5)``."""
    out = np.array(k, dtype=np.float64)
    out[0, 0] *= sx
    out[0, 1] *= sx
    out[1, 1] *= sy
    out[0, 2] = sx * (k[0, 2] + 0.5) - 0.5
    out[1, 2] = sy * (k[1, 2] + 0.5) - 0.5
    return out


def look_rotation(forward: np.ndarray, up: np.ndarray) -> np.ndarray:
    """Camera-to-world rotation ``[3, 3]`` with columns (right, down, forward); no roll about ``forward``."""
    f = forward / np.linalg.norm(forward)
    right = np.cross(f, up)
    if np.linalg.norm(right) < 1e-9:  # looking straight along up: pick any horizontal right
        right = np.cross(f, np.array([1.0, 0.0, 0.0]) if abs(f[0]) < 0.9 else np.array([0.0, 1.0, 0.0]))
    right /= np.linalg.norm(right)
    down = np.cross(f, right)
    return np.stack([right, down, f], axis=1)


@dataclass(frozen=True, eq=False)
class ViewCamera:
    """A pinhole camera to render: pose, intrinsics and image size."""

    world_to_cam: np.ndarray  # [4, 4] float64
    intrinsics: np.ndarray  # [3, 3] float64, pixels
    width: int
    height: int

    @property
    def cam_to_world(self) -> np.ndarray:
        return invert_rigid(self.world_to_cam)

    @property
    def centre(self) -> np.ndarray:
        return self.cam_to_world[:3, 3]

    def resized(self, width: int, height: int) -> ViewCamera:
        """The same view at another resolution (intrinsics scaled exactly)."""
        k = scale_intrinsics(self.intrinsics, width / self.width, height / self.height)
        return ViewCamera(self.world_to_cam, k, int(width), int(height))

    def shifted(self, origin: np.ndarray) -> ViewCamera:
        """The same camera for a world whose coordinates had ``origin`` subtracted."""
        m = self.world_to_cam.copy()
        m[:3, 3] += m[:3, :3] @ np.asarray(origin, np.float64)
        return ViewCamera(m, self.intrinsics, self.width, self.height)

    def gl_projection(self, near: float = 0.05, far: float = 5000.0) -> np.ndarray:
        """4x4 camera (OpenCV) -> clip matrix: NDC x = 2 (u + 0.5) / W - 1, y = 1 - 2 (v + 0.5) / H."""
        k, w, h = self.intrinsics, self.width, self.height
        p = np.zeros((4, 4))
        p[0, 0], p[0, 1], p[0, 2] = 2 * k[0, 0] / w, 2 * k[0, 1] / w, 2 * (k[0, 2] + 0.5) / w - 1
        p[1, 1], p[1, 2] = -2 * k[1, 1] / h, 1 - 2 * (k[1, 2] + 0.5) / h
        p[2, 2], p[2, 3] = (far + near) / (far - near), -2 * far * near / (far - near)
        p[3, 2] = 1.0
        return p

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixels ``[N, 2]`` and camera z ``[N]`` of world points ``[N, 3]``."""
        p = points @ self.world_to_cam[:3, :3].T + self.world_to_cam[:3, 3]
        z = p[:, 2]
        safe = np.where(np.abs(z) > 1e-9, z, 1e-9)
        k = self.intrinsics
        u = k[0, 0] * p[:, 0] / safe + k[0, 1] * p[:, 1] / safe + k[0, 2]
        v = k[1, 1] * p[:, 1] / safe + k[1, 2]
        return np.stack([u, v], axis=1), z

    def ray(self, u: float, v: float) -> tuple[np.ndarray, np.ndarray]:
        """World origin and unit direction of the ray through pixel (u, v)."""
        k = self.intrinsics
        y = (v - k[1, 2]) / k[1, 1]
        x = (u - k[0, 2] - k[0, 1] * y) / k[0, 0]
        c2w = self.cam_to_world
        d = c2w[:3, :3] @ np.array([x, y, 1.0])
        return c2w[:3, 3], d / np.linalg.norm(d)


class NavCamera:
    """Orbit / pan / zoom / fly navigation around ``target`` in a z-up navigation frame.

    The navigation frame is the world (``frame_to_world`` = identity, optionally rotated so that
    another axis is up) or, in follow-ego mode, the ego frame at the current time.
    """

    def __init__(self, fov_y_deg: float = 60.0):
        self.target = np.zeros(3)
        self.yaw = 0.0  # radians, 0 looks along +x
        self.pitch = -0.35  # radians, negative looks down
        self.distance = 20.0
        self.fov_y_deg = fov_y_deg
        self.up_to_world = Z_UP.copy()

    def copy(self) -> NavCamera:
        out = NavCamera(self.fov_y_deg)
        out.target, out.yaw, out.pitch, out.distance = self.target.copy(), self.yaw, self.pitch, self.distance
        out.up_to_world = self.up_to_world.copy()
        return out

    @property
    def forward(self) -> np.ndarray:
        cp = math.cos(self.pitch)
        return np.array([cp * math.cos(self.yaw), cp * math.sin(self.yaw), math.sin(self.pitch)])

    @property
    def eye(self) -> np.ndarray:
        return self.target - self.distance * self.forward

    def cam_to_frame(self) -> np.ndarray:
        """Camera pose ``[4, 4]`` in the navigation frame's world axes (up rotation applied)."""
        m = np.eye(4)
        m[:3, :3] = self.up_to_world @ look_rotation(self.forward, np.array([0.0, 0.0, 1.0]))
        m[:3, 3] = self.up_to_world @ self.eye
        return m

    def view(self, width: int, height: int, frame_to_world: np.ndarray | None = None) -> ViewCamera:
        cam_to_world = self.cam_to_frame() if frame_to_world is None else frame_to_world @ self.cam_to_frame()
        return ViewCamera(invert_rigid(cam_to_world), intrinsics_from_fov(width, height, self.fov_y_deg), width, height)

    # --- navigation (dx, dy in pixels of a viewport ``height`` tall) ---
    def orbit(self, dx: float, dy: float, speed: float = 0.005) -> None:
        self.yaw -= dx * speed
        self.pitch = float(np.clip(self.pitch - dy * speed, -1.55, 1.55))

    def look(self, dx: float, dy: float, speed: float = 0.003) -> None:
        """Mouse look: rotate about the eye (the target moves)."""
        eye = self.eye
        self.orbit(dx, dy, speed)
        self.target = eye + self.distance * self.forward

    def pan(self, dx: float, dy: float, height: int) -> None:
        rot = look_rotation(self.forward, np.array([0.0, 0.0, 1.0]))
        scale = 2 * self.distance * math.tan(math.radians(self.fov_y_deg) / 2) / max(height, 1)
        self.target = self.target - rot[:, 0] * dx * scale - rot[:, 1] * dy * scale

    def zoom(self, factor: float) -> None:
        self.distance = float(np.clip(self.distance * factor, 0.05, 1e5))

    def fly(self, right: float, forward: float, up: float, metres: float) -> None:
        """Move eye and target together along the view axes (up is the frame's z)."""
        rot = look_rotation(self.forward, np.array([0.0, 0.0, 1.0]))
        move = rot[:, 0] * right + self.forward * forward + np.array([0.0, 0.0, 1.0]) * up
        self.target = self.target + move * metres

    def set_pose(self, cam_to_frame: np.ndarray, distance: float | None = None) -> None:
        """Look from ``cam_to_frame``'s centre along its z axis (roll dropped), keeping or setting the distance."""
        rot = self.up_to_world.T @ cam_to_frame[:3, :3]
        f = rot[:, 2]
        self.yaw = math.atan2(f[1], f[0])
        self.pitch = float(np.clip(math.asin(np.clip(f[2], -1, 1)), -1.55, 1.55))
        self.distance = distance or self.distance
        self.target = self.up_to_world.T @ cam_to_frame[:3, 3] + self.distance * self.forward

    def frame_points(self, points: np.ndarray) -> None:
        """Keep the direction; move so that the bulk (2-98th percentiles) of ``points`` (frame axes) fills the view."""
        if len(points) == 0:
            return
        p = points @ self.up_to_world  # into nav axes
        lo, hi = np.percentile(p, 2, axis=0), np.percentile(p, 98, axis=0)
        radius = max(0.5 * float(np.linalg.norm(hi - lo)), 0.1)
        self.target = 0.5 * (lo + hi)
        self.distance = 1.1 * radius / math.sin(math.radians(self.fov_y_deg) / 2)


def rig_camera(cam_to_world: np.ndarray, intrinsics: np.ndarray, image_size: tuple[int, int]) -> ViewCamera:
    """A rig camera at its pose ``[4, 4]`` with the rig's exact K and image size (H, W)."""
    height, width = image_size
    return ViewCamera(invert_rigid(np.asarray(cam_to_world, np.float64)), np.asarray(intrinsics, np.float64), width, height)


def fit_rect(src_w: int, src_h: int, dst_w: int, dst_h: int) -> tuple[int, int, int, int]:
    """Letterbox (x, y, w, h) of an image ``src`` scaled to fit inside ``dst`` keeping its aspect."""
    s = min(dst_w / src_w, dst_h / src_h)
    w, h = max(1, round(src_w * s)), max(1, round(src_h * s))
    return (dst_w - w) // 2, (dst_h - h) // 2, w, h


def ego_pose(recon, t: float) -> np.ndarray:
    """Ego-to-world ``[4, 4]`` float64 at normalised time t (SE(3) interpolation of the keyframes)."""
    return recon.ego_to_world_at(float(t)).numpy()


class CameraController:
    """Which camera the 3D view shows: the navigation camera (in the world or following the ego),
    or a rig camera snapped at the current time. ``up`` is the world's up axis (``Loaded.info["up"]``):
    the window and the headless renders both build their camera with it."""

    def __init__(self, fov_y_deg: float = 60.0, up: str = "z"):
        self.nav = NavCamera(fov_y_deg)
        self.nav.up_to_world = up_rotation(up)
        self.rig_index: int | None = None  # snapped to this rig camera
        self.follow_ego = False
        self.fly_mode = False  # left drag looks around instead of orbiting

    def frame_to_world(self, recon, t: float) -> np.ndarray | None:
        return ego_pose(recon, t) if self.follow_ego and recon.num_views else None

    def view(self, recon, t: float, width: int, height: int) -> ViewCamera:
        """The camera at time t for a viewport of ``width`` x ``height`` (rig views keep the rig K/size)."""
        if self.rig_index is not None and self.rig_index < recon.num_views:
            return rig_camera(
                recon.cam_to_world_at(float(t))[self.rig_index].numpy(), recon.intrinsics[self.rig_index], recon.image_size
            )
        return self.nav.view(width, height, self.frame_to_world(recon, t))

    def snap(self, index: int | None) -> None:
        self.rig_index = index

    def unsnap(self, recon, t: float) -> None:
        """Leave the rig camera, continuing from its pose with the navigation camera."""
        if self.rig_index is None:
            return
        cam_to_world = recon.cam_to_world_at(float(t))[self.rig_index].numpy()
        frame = self.frame_to_world(recon, t)
        self.nav.set_pose(cam_to_world if frame is None else invert_rigid(frame) @ cam_to_world, distance=10.0)
        self.rig_index = None

    def set_follow(self, recon, t: float, on: bool) -> None:
        """Switch follow-ego mode without moving the view at time t."""
        if on == self.follow_ego or not recon.num_views:
            return
        cam = self.nav.cam_to_frame()
        ego = ego_pose(recon, t)
        self.nav.set_pose(invert_rigid(ego) @ cam if on else ego @ cam)
        self.follow_ego = on

    def reset(self, recon, t: float, points: np.ndarray | None = None) -> None:
        """A chase view above and behind the ego (driving scenes), or frame all (other files)."""
        self.rig_index = None
        if recon.num_views:
            ego = ego_pose(recon, t) if not self.follow_ego else np.eye(4)
            forward = ego[:3, 0]
            self.nav.yaw = math.atan2(forward[1], forward[0])
            self.nav.pitch = -0.45
            self.nav.distance = 28.0
            self.nav.target = ego[:3, 3] + 10.0 * np.array([math.cos(self.nav.yaw), math.sin(self.nav.yaw), 0.0])
        elif points is not None:
            self.nav.yaw, self.nav.pitch = -2.2, -0.4
            self.nav.frame_points(points)
