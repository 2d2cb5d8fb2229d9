"""The frame-pair scene format, version 1 (``scene.npz``), documented in docs/scene-format.md.

A ``FramePair`` mirrors the file: uint8 images and float32/float64 arrays exactly as stored. Models
convert to float tensors at their boundary.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np

from drivingscene.data.npz import load_format, save_npz
from drivingscene.data.validate import (
    FORMAT_NAME,
    FORMAT_VERSION,
    OPTIONAL,
    OPTIONAL_KEYS,
    REQUIRED,
    REQUIRED_KEYS,
    validate_arrays,
)
from drivingscene.errors import InputError, Problem, SceneFormatError

# Beyond this distance from the world's origin float32 positions lose millimetres (1e4 m: ~1 mm
# steps; 6.4e6 m: half a metre), and a pair is moved to its first ego pose (`FramePair.origin`).
FAR_FROM_ORIGIN_M = 1e4
POSE_FIELDS = ("ego_to_world", "eval_ego_to_world", "camera_ego_to_world", "eval_camera_ego_to_world")


@dataclass(frozen=True, eq=False)
class FramePair:
    """Two keyframes of a rig of V cameras, with optional ground truth and evaluation frames."""

    images: np.ndarray  # [2, V, H, W, 3] uint8
    intrinsics: np.ndarray  # [V, 3, 3] float32, pixels
    cam_to_ego: np.ndarray  # [V, 4, 4] float32, OpenCV camera axes, metres
    ego_to_world: np.ndarray  # [2, 4, 4] float64
    timestamps: np.ndarray  # [2] float64, seconds
    camera_names: tuple[str, ...]  # [V]
    gt_depth: np.ndarray | None = None  # [2, V, H, W] float32, z-depth, 0 = unknown or sky
    gt_flow: np.ndarray | None = None  # [2, V, H, W, 2] float32, pixels; [0] 0->1, [1] 1->0
    gt_scene_flow: np.ndarray | None = None  # [2, V, H, W, 3] float32, world metres
    gt_dynamic: np.ndarray | None = None  # [2, V, H, W] bool
    eval_images: np.ndarray | None = None  # [M, V, H, W, 3] uint8
    eval_timestamps: np.ndarray | None = None  # [M] float64, seconds
    eval_ego_to_world: np.ndarray | None = None  # [M, 4, 4] float64
    eval_dynamic: np.ndarray | None = None  # [M, V, H, W] bool
    valid_mask: np.ndarray | None = None  # [V, H, W] bool, False: not the world (ego body, hood)
    camera_ego_to_world: np.ndarray | None = None  # [2, V, 4, 4] float64, ego pose at each image's capture
    camera_timestamps: np.ndarray | None = None  # [2, V] float64, seconds, each image's capture time
    eval_camera_ego_to_world: np.ndarray | None = None  # [M, V, 4, 4] float64
    eval_camera_timestamps: np.ndarray | None = None  # [M, V] float64, seconds
    origin: np.ndarray | None = None  # [3] float64: the world point every pose above is relative to

    def __post_init__(self) -> None:
        """A world frame far from its origin (UTM, ECEF: 6.4e6 m) is moved to the first ego pose,
        kept in ``origin``: every float32 computation downstream (Gaussian centres, cameras) then
        works with metres near zero instead of steps of half a metre."""
        if self.origin is not None:
            return
        poses = [
            p
            for p in (self.ego_to_world, self.eval_ego_to_world, self.camera_ego_to_world, self.eval_camera_ego_to_world)
            if p is not None
        ]
        if max(float(np.abs(p[..., :3, 3]).max()) for p in poses) <= FAR_FROM_ORIGIN_M:
            return
        origin = np.array(self.ego_to_world[0, :3, 3], dtype=np.float64)
        object.__setattr__(self, "origin", origin)
        for name in POSE_FIELDS:
            value = getattr(self, name)
            if value is not None:
                moved = np.array(value, dtype=np.float64)
                moved[..., :3, 3] -= origin
                object.__setattr__(self, name, moved)

    @property
    def num_views(self) -> int:
        return int(self.images.shape[1])

    @property
    def image_size(self) -> tuple[int, int]:
        """(H, W) in pixels."""
        return int(self.images.shape[2]), int(self.images.shape[3])

    @property
    def num_eval(self) -> int:
        return 0 if self.eval_images is None else int(self.eval_images.shape[0])

    @property
    def duration(self) -> float:
        """Seconds between the two keyframes."""
        return float(self.timestamps[1] - self.timestamps[0])

    def normalised_time(self, seconds: np.ndarray | float) -> np.ndarray:
        """Map timestamps in seconds to t in [0, 1] between the keyframes."""
        return (np.asarray(seconds, dtype=np.float64) - self.timestamps[0]) / self.duration

    def seconds(self, t: np.ndarray | float) -> np.ndarray:
        """Map normalised time t to seconds."""
        return self.timestamps[0] + np.asarray(t, dtype=np.float64) * self.duration

    def camera_ego_poses(self) -> np.ndarray:
        """``[2, V, 4, 4]`` float64 ego pose at each keyframe image's capture: ``camera_ego_to_world``,
        else the keyframe's ``ego_to_world`` for every camera."""
        if self.camera_ego_to_world is not None:
            return self.camera_ego_to_world
        return np.broadcast_to(self.ego_to_world[:, None], (2, self.num_views, 4, 4))

    def eval_camera_ego_poses(self) -> np.ndarray:
        """``[M, V, 4, 4]`` float64 ego pose at each intermediate image's capture (as `camera_ego_poses`)."""
        if self.eval_camera_ego_to_world is not None:
            return self.eval_camera_ego_to_world
        return np.broadcast_to(self.eval_ego_to_world[:, None], (self.num_eval, self.num_views, 4, 4))

    def eval_camera_times(self) -> np.ndarray:
        """``[M, V]`` normalised capture time of each intermediate image."""
        seconds = self.eval_camera_timestamps
        if seconds is None:
            seconds = np.broadcast_to(self.eval_timestamps[:, None], (self.num_eval, self.num_views))
        return self.normalised_time(seconds)

    def world_mask(self) -> np.ndarray:
        """``[V, H, W]`` bool: pixels that see the world (``valid_mask``, all True without one)."""
        if self.valid_mask is None:
            return np.ones((self.num_views, *self.image_size), dtype=bool)
        return self.valid_mask

    def has(self, key: str) -> bool:
        return getattr(self, key, None) is not None

    def to_arrays(self) -> dict[str, np.ndarray]:
        """The file's arrays, ready for ``save_npz``."""
        arrays: dict[str, np.ndarray] = {
            "format": np.array(FORMAT_NAME),
            "version": np.array(FORMAT_VERSION, dtype=np.int64),
        }
        for f in fields(self):
            value = getattr(self, f.name)
            if value is None:
                continue
            arrays[f.name] = np.array(value, dtype=np.str_) if f.name == "camera_names" else value
        return arrays

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray], source: str = "<memory>") -> FramePair:
        """Validate ``arrays`` and wrap them. Raises ``SceneFormatError`` listing every problem."""
        problems = validate_arrays(arrays, source)
        if problems:
            raise SceneFormatError(problems)
        kwargs = {k: arrays[k] for k in REQUIRED_KEYS if k not in ("format", "version")}
        kwargs["camera_names"] = tuple(str(n) for n in arrays["camera_names"])
        kwargs.update({k: arrays[k] for k in OPTIONAL_KEYS if k in arrays})
        return cls(**kwargs)

    def validate(self, source: str = "<memory>") -> list[Problem]:
        return validate_arrays(self.to_arrays(), source)

    def select_views(self, views: list[int]) -> FramePair:
        """A pair holding only the given cameras (in that order)."""
        idx = np.asarray(views, dtype=np.int64)
        out = {}
        for f in fields(self):
            value = getattr(self, f.name)
            if value is None or f.name in ("ego_to_world", "timestamps", "eval_timestamps", "eval_ego_to_world", "origin"):
                out[f.name] = value
            elif f.name == "camera_names":
                out[f.name] = tuple(value[i] for i in idx)
            elif f.name in ("intrinsics", "cam_to_ego", "valid_mask"):
                out[f.name] = value[idx]
            else:
                out[f.name] = value[:, idx]
        return FramePair(**out)


def validate_frame_pair_file(path: str | os.PathLike) -> list[Problem]:
    """Every problem of a scene file; an empty list means valid."""
    try:
        arrays = load_format(path, REQUIRED, OPTIONAL)
    except SceneFormatError as e:
        return list(e.problems)
    except InputError as e:
        return [_read_problem(str(path), str(e))]
    return validate_arrays(arrays, str(path))


def _read_problem(source: str, message: str) -> Problem:
    """The ``Problem`` of a file that could not be read (``load_format``'s one-line message)."""
    text = message.removeprefix(f"{source}: ")
    match = re.fullmatch(r"(?:([\w\[\].]+): )?expected (.*?), found (.*)", text)
    if match is None:
        return Problem(source, "<file>", "a readable .npz scene file", text)
    return Problem(source, match.group(1) or "<file>", match.group(2), match.group(3))


def load_frame_pair(path: str | os.PathLike) -> FramePair:
    """Load and validate a ``scene.npz``.

    Raises:
        InputError: unreadable file; SceneFormatError: invalid contents (one line, every problem kept).
    """
    return FramePair.from_arrays(load_format(path, REQUIRED, OPTIONAL), source=str(path))


def save_frame_pair(pair: FramePair, path: str | os.PathLike, *, compress: bool = True) -> Path:
    """Validate, then write atomically and deterministically."""
    problems = pair.validate(str(path))
    if problems:
        raise SceneFormatError(problems)
    return save_npz(path, pair.to_arrays(), compress=compress)
