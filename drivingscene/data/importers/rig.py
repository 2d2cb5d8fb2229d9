"""Your own rig -> frame pair (``drivingscene import rig FOLDER``); the folder layout and the
``rig.json`` schema are in docs/importing.md ("Your own rig") and `rig_schema`.

- Cameras keep their names and are ordered around the car (front, then clockwise seen from above).
- Distorted images are resampled to pinhole images of the same size (`undistort`); pixels without
  a source, and those black in the camera's mask PNG, are invalid (``valid_mask`` False).
- Then everything is fitted to the output size (`common.Fit`: images, intrinsics, masks).
- Frames ``I J`` are the keyframes; ``--eval`` frames strictly between them become eval frames.
- Each image's capture time and ego pose: the frame's ``camera_timestamps`` /
  ``camera_ego_to_world`` where given (stored per image), else the frame's own.
- LiDAR: points in the ego frame at the frame's time -> world -> the ego at each image's capture
  -> the camera, nearest point per pixel (`common.lidar_depth`); none on invalid pixels.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from drivingscene.data.frame_pair import FramePair
from drivingscene.data.importers.common import Fit, lidar_depth, order_around_car, read_rgb
from drivingscene.data.importers.rig_schema import Rig, RigCamera, RigFrame, load_rig
from drivingscene.data.importers.undistort import Undistortion
from drivingscene.errors import InputError

__all__ = ["import_rig", "load_rig"]


@dataclass(frozen=True)
class _Camera:
    """One camera of the rig on its way to the output size."""

    index: int  # in rig.json's cameras
    spec: RigCamera
    undistortion: Undistortion  # at the camera's own size
    fit: Fit  # undistorted image -> output size

    @property
    def intrinsics(self) -> np.ndarray:
        """``[3, 3]`` float64 of the output image."""
        return self.fit.intrinsics(self.undistortion.intrinsics)

    @property
    def valid(self) -> np.ndarray:
        """``[H, W]`` bool of the output image."""
        return self.fit.mask(self.undistortion.valid)


@dataclass
class _Frame:
    images: np.ndarray  # [V, H, W, 3] uint8
    camera_ego_to_world: np.ndarray  # [V, 4, 4] float64
    camera_seconds: np.ndarray  # [V] float64
    per_camera: bool  # the frame gave per-camera times or poses
    depth: np.ndarray | None  # [V, H, W] float32, None without LiDAR


def _read_mask(path: Path, size: tuple[int, int], where: str) -> np.ndarray:
    """bool ``[H, W]`` from a mask PNG: True (white, >= 128) where the camera sees the world."""
    mask = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE) if path.is_file() else None
    if mask is None:
        found = "unreadable data" if path.exists() else "no such file"
        raise InputError(f"{path}: expected a readable mask PNG ({where}), found {found}")
    if mask.shape != size:
        raise InputError(
            f"{path}: expected {size[1]}x{size[0]} pixels like the camera's images ({where}), found {mask.shape[1]}x{mask.shape[0]}"
        )
    return mask >= 128


def _cameras(rig: Rig, size: tuple[int, int] | None, fit: str) -> list[_Camera]:
    """The cameras in order around the car, undistorted and fitted to ``size`` (None: their own)."""
    order = order_around_car(np.stack([c.cam_to_ego for c in rig.cameras]))
    if size is None:
        sizes = {c.size for c in rig.cameras}
        if len(sizes) > 1:
            found = ", ".join(f"{c.name} {c.size[1]}x{c.size[0]}" for c in rig.cameras)
            raise InputError(f"{rig.source}: cameras: expected one image size without --res, found {found}; pass --res HxW")
    out = []
    for i in order:
        spec = rig.cameras[i]
        where = f"{rig.source.name}: cameras[{i}].mask of {spec.name}"
        mask = None if spec.mask is None else _read_mask(spec.mask, spec.size, where)
        undistortion = Undistortion.make(spec.intrinsics, spec.distortion, spec.coeffs, spec.size, mask)
        if not undistortion.valid.any():
            raise InputError(
                f"{rig.source}: cameras[{i}]: expected some pixels of {spec.name} to see the world, found none (mask or distortion)"
            )
        out.append(_Camera(int(i), spec, undistortion, Fit.make(spec.size, size or spec.size, fit)))
    return out


def _image(path: Path, camera: _Camera, where: str) -> np.ndarray:
    """uint8 ``[H, W, 3]`` at the output size from one image file."""
    if not path.is_file():
        raise InputError(f"{where}: expected an existing image file, found no file {path}")
    image = read_rgb(path)
    height, width = camera.spec.size
    if image.shape[:2] != (height, width):
        raise InputError(
            f"{path}: expected {width}x{height} pixels (width x height of camera {camera.spec.name}, "
            f"cameras[{camera.index}]), found {image.shape[1]}x{image.shape[0]}"
        )
    return camera.fit.image(camera.undistortion.image(image))


def _lidar_points(path: Path, where: str) -> np.ndarray:
    """``[N, 3]`` float64 points from a .npy of shape [N, 3+]."""
    try:
        points = np.load(path, allow_pickle=False)
    except FileNotFoundError:
        raise InputError(f"{where}: expected an existing LiDAR .npy file, found no file {path}") from None
    except (OSError, ValueError) as e:
        raise InputError(f"{path}: expected a .npy array of LiDAR points [N, 3+], found unreadable data ({e})") from None
    if points.ndim != 2 or points.shape[1] < 3 or points.dtype.kind not in "fiu":
        raise InputError(
            f"{path}: expected a numeric array of shape [N, 3+] (x, y, z in the ego frame, metres), found {points.dtype} {list(points.shape)}"
        )
    return points[:, :3].astype(np.float64)


def _frame(rig: Rig, index: int, cameras: list[_Camera]) -> _Frame:
    frame: RigFrame = rig.frames[index]
    where = f"{rig.source}: frames[{index}]"
    images, poses, seconds, depths = [], [], [], []
    points = None if frame.lidar is None else _lidar_points(frame.lidar, f"{where}.lidar")
    for cam in cameras:
        name = cam.spec.name
        images.append(_image(frame.images[name], cam, f"{where}.images.{name}"))
        poses.append(frame.camera_ego_to_world.get(name, frame.ego_to_world))
        seconds.append(frame.camera_timestamps.get(name, frame.timestamp))
        if points is not None:
            to_cam = np.linalg.inv(cam.spec.cam_to_ego) @ np.linalg.inv(poses[-1]) @ frame.ego_to_world
            depth = lidar_depth(points, to_cam, cam.intrinsics, cam.fit.dst)
            depths.append(np.where(cam.valid, depth, 0.0).astype(np.float32))
    per_camera = bool(frame.camera_timestamps or frame.camera_ego_to_world)
    depth = None if points is None else np.stack(depths)
    return _Frame(np.stack(images), np.stack(poses), np.array(seconds, dtype=np.float64), per_camera, depth)


def _check_indices(rig: Rig, frames: tuple[int, int], eval_frames: tuple[int, ...]) -> list[int]:
    """The keyframes and eval frames as [I, J, K...] (K increasing), checked against the rig."""
    n = len(rig.frames)
    for flag, values in (("--frames", frames), ("--eval", eval_frames)):
        for k in values:
            if not 0 <= k < n:
                raise InputError(f"{flag}: expected frame indices in 0..{n - 1} ({rig.source} has {n} frames), found {k}")
    i, j = frames
    if not i < j:
        raise InputError(f"--frames: expected I before J (frames are in time order in {rig.source.name}), found {i} {j}")
    outside = [k for k in eval_frames if not i < k < j]
    if outside:
        raise InputError(f"--eval: expected frames strictly between the keyframes {i} and {j}, found {outside[0]}")
    return [i, j, *sorted(set(eval_frames))]


def import_rig(
    folder: str | Path,
    frames: tuple[int, int] = (0, 1),
    eval_frames: tuple[int, ...] = (),
    size: tuple[int, int] | None = None,
    fit: str = "crop",
) -> FramePair:
    """Two frames of a rig folder as a frame pair, with frames between them as eval frames.

    Args:
        folder: holds ``rig.json`` and the files it names (docs/importing.md).
        frames: indices (I, J), I < J, into rig.json's ``frames``: the keyframes.
        eval_frames: indices strictly between I and J: the eval frames.
        size: output (H, W); None keeps the images' size (then every camera must have the same).
        fit: "crop" (cover, centre-crop) or "pad" (fit inside, padding masked).

    Raises:
        InputError: one line naming the file, the field and what was expected.
    """
    rig = load_rig(folder)
    indices = _check_indices(rig, tuple(frames), tuple(eval_frames))
    cameras = _cameras(rig, size, fit)
    loaded = [_frame(rig, k, cameras) for k in indices]
    keys, evals = loaded[:2], loaded[2:]
    valid = np.stack([c.valid for c in cameras])
    per_camera = any(f.per_camera for f in loaded)
    out = dict(
        images=np.stack([f.images for f in keys]),
        intrinsics=np.stack([c.intrinsics for c in cameras]).astype(np.float32),
        cam_to_ego=np.stack([c.spec.cam_to_ego for c in cameras]).astype(np.float32),
        ego_to_world=np.stack([rig.frames[k].ego_to_world for k in indices[:2]]),
        timestamps=np.array([rig.frames[k].timestamp for k in indices[:2]]),
        camera_names=tuple(c.spec.name for c in cameras),
    )
    if not valid.all():
        out["valid_mask"] = valid
    if per_camera:
        out["camera_ego_to_world"] = np.stack([f.camera_ego_to_world for f in keys])
        out["camera_timestamps"] = np.stack([f.camera_seconds for f in keys])
    if any(f.depth is not None for f in keys):  # a keyframe without LiDAR: depth unknown (0)
        zeros = np.zeros(valid.shape, np.float32)
        out["gt_depth"] = np.stack([zeros if f.depth is None else f.depth for f in keys])
    if evals:
        out["eval_images"] = np.stack([f.images for f in evals])
        out["eval_timestamps"] = np.array([rig.frames[k].timestamp for k in indices[2:]])
        out["eval_ego_to_world"] = np.stack([rig.frames[k].ego_to_world for k in indices[2:]])
        if per_camera:
            out["eval_camera_ego_to_world"] = np.stack([f.camera_ego_to_world for f in evals])
            out["eval_camera_timestamps"] = np.stack([f.camera_seconds for f in evals])
    return FramePair(**out)
