"""Shared pieces of the importers: output size, image fitting, LiDAR to sparse depth, camera order.

Image fitting ("crop", the default): an image of any size and aspect is scaled so that it covers
the output size, then centre-cropped; intrinsics follow exactly (pixel centres at integer
coordinates: u' = (u + 0.5) s - 0.5 - crop). "pad" scales it to fit inside and pads with black,
marking the padding invalid in ``valid_mask``. Scaling down uses area averaging (OpenCV).
"""

from __future__ import annotations

import argparse
import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from drivingscene.errors import InputError

FIT_MODES = ("crop", "pad")
# LiDAR points used for gt_depth (z-depth, metres), as in the depth-evaluation literature.
LIDAR_NEAR, LIDAR_FAR = 0.1, 80.0
# Largest output image an importer writes (pixels per side).
MAX_SIDE = 4096


def parse_resolution(text: str) -> tuple[int, int]:
    """argparse type: ``HxW`` (e.g. ``176x320``) -> (H, W), each in [16, MAX_SIDE]."""
    parts = text.lower().split("x")
    try:
        height, width = (int(p) for p in parts)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected HxW in pixels such as 176x320, found {text!r}") from None
    if not (16 <= height <= MAX_SIDE and 16 <= width <= MAX_SIDE):
        raise argparse.ArgumentTypeError(f"expected H and W between 16 and {MAX_SIDE} pixels, found {text!r}")
    return height, width


@dataclass(frozen=True)
class Fit:
    """How a source image of ``src`` (H, W) maps onto the output ``dst`` (H, W):
    u_out = (u_src + 0.5) * sx - 0.5 - offset[0], likewise v with sy and offset[1], where
    (sy, sx) = scaled_size / src."""

    src: tuple[int, int]
    dst: tuple[int, int]
    scale: float  # nominal; the image is resized to `scaled_size` (whole pixels)
    offset: tuple[float, float]  # (x, y) pixels cropped (> 0) or padded (< 0), at the output scale

    @classmethod
    def make(cls, src: tuple[int, int], dst: tuple[int, int], mode: str = "crop") -> Fit:
        if mode not in FIT_MODES:
            raise InputError(f"--fit: expected one of {', '.join(FIT_MODES)}, found {mode!r}")
        ratios = (dst[0] / src[0], dst[1] / src[1])
        scale = max(ratios) if mode == "crop" else min(ratios)
        scaled = (src[0] * scale, src[1] * scale)
        # integer offsets so that cropping/padding moves whole pixels
        offset = (float(math.floor((scaled[1] - dst[1]) / 2)), float(math.floor((scaled[0] - dst[0]) / 2)))
        return cls(tuple(src), tuple(dst), scale, offset)

    @property
    def scaled_size(self) -> tuple[int, int]:
        """(H, W) of the source after scaling, before the crop or pad."""
        return max(1, round(self.src[0] * self.scale)), max(1, round(self.src[1] * self.scale))

    def intrinsics(self, k: np.ndarray) -> np.ndarray:
        """``[3, 3]`` intrinsics of the fitted image (per-axis scale of the whole-pixel resize)."""
        sx, sy = self.scaled_size[1] / self.src[1], self.scaled_size[0] / self.src[0]
        out = np.array(k, dtype=np.float64)
        out[0, :2] *= sx
        out[1, 1] *= sy
        out[0, 2] = (k[0, 2] + 0.5) * sx - 0.5 - self.offset[0]
        out[1, 2] = (k[1, 2] + 0.5) * sy - 0.5 - self.offset[1]
        return out

    def _place(self, scaled: np.ndarray, fill) -> np.ndarray:
        height, width = self.dst
        out = np.full((height, width, *scaled.shape[2:]), fill, dtype=scaled.dtype)
        ox, oy = int(self.offset[0]), int(self.offset[1])
        # source window [sy0, sy1) x [sx0, sx1) lands at [dy0, ...) x [dx0, ...)
        sy0, sx0 = max(oy, 0), max(ox, 0)
        dy0, dx0 = max(-oy, 0), max(-ox, 0)
        h = min(scaled.shape[0] - sy0, height - dy0)
        w = min(scaled.shape[1] - sx0, width - dx0)
        out[dy0 : dy0 + h, dx0 : dx0 + w] = scaled[sy0 : sy0 + h, sx0 : sx0 + w]
        return out

    def image(self, image: np.ndarray) -> np.ndarray:
        """uint8 ``[H0, W0, 3]`` -> ``[H, W, 3]`` (area-averaged when shrinking)."""
        sh, sw = self.scaled_size
        interp = cv2.INTER_AREA if self.scale < 1 else cv2.INTER_LINEAR
        scaled = cv2.resize(image, (sw, sh), interpolation=interp) if (sh, sw) != image.shape[:2] else image
        return self._place(scaled, 0)

    def mask(self, mask: np.ndarray) -> np.ndarray:
        """bool ``[H0, W0]`` -> ``[H, W]``: an output pixel is valid when most of its source area is;
        padding is invalid."""
        sh, sw = self.scaled_size
        frac = cv2.resize(mask.astype(np.float32), (sw, sh), interpolation=cv2.INTER_AREA)
        return self._place(frac > 0.5, False)

    def valid(self) -> np.ndarray:
        """bool ``[H, W]``: output pixels that come from the source image (False in padding)."""
        return self.mask(np.ones(self.src, dtype=bool))


def lidar_depth(
    points: np.ndarray,  # [N, 3] in the frame of `to_cam`'s source (e.g. world), metres
    to_cam: np.ndarray,  # [4, 4] points' frame -> camera (OpenCV axes)
    intrinsics: np.ndarray,  # [3, 3] of the output image
    size: tuple[int, int],  # (H, W)
    near: float = LIDAR_NEAR,
    far: float = LIDAR_FAR,
) -> np.ndarray:
    """Sparse z-depth ``[H, W]`` float32 from LiDAR points: each point within [near, far] metres in
    front of the camera goes to its nearest pixel; where several land, the nearest wins; 0 elsewhere."""
    height, width = size
    pts = np.asarray(points, dtype=np.float64)[:, :3]
    cam = pts @ to_cam[:3, :3].T + to_cam[:3, 3]
    z = cam[:, 2]
    keep = np.isfinite(cam).all(axis=1) & (z >= near) & (z <= far)
    cam, z = cam[keep], z[keep]
    uvw = cam @ np.asarray(intrinsics, dtype=np.float64).T
    u = np.rint(uvw[:, 0] / z).astype(np.int64)
    v = np.rint(uvw[:, 1] / z).astype(np.int64)
    inside = (u >= 0) & (u < width) & (v >= 0) & (v < height)
    u, v, z = u[inside], v[inside], z[inside]
    depth = np.full(height * width, np.inf)
    np.minimum.at(depth, v * width + u, z)
    depth[~np.isfinite(depth)] = 0.0
    return depth.reshape(height, width).astype(np.float32)


def camera_yaw_deg(cam_to_ego: np.ndarray) -> np.ndarray:
    """``[V]`` yaw of each camera's optical axis in the ego frame, degrees (0 forward, + left)."""
    axis = np.asarray(cam_to_ego)[:, :3, 2]
    return np.degrees(np.arctan2(axis[:, 1], axis[:, 0]))


def order_around_car(cam_to_ego: np.ndarray) -> np.ndarray:
    """Camera indices ordered as the nuScenes rig: from the front clockwise seen from above
    (front, front-right, back-right, back, back-left, front-left)."""
    # a camera up to 30 deg left of straight ahead still comes first (the front camera)
    clockwise = np.remainder(30.0 - camera_yaw_deg(cam_to_ego), 360.0)
    return np.argsort(clockwise, kind="stable")


def rigid_from_quaternion(wxyz, translation) -> np.ndarray:
    """``[4, 4]`` float64 from a (w, x, y, z) quaternion (normalised) and a translation in metres."""
    import torch

    from drivingscene.geometry.se3 import quat_to_matrix

    q = torch.tensor([float(c) for c in wxyz], dtype=torch.float64)
    if not (torch.isfinite(q).all() and q.norm() > 0):
        raise ValueError(f"expected a non-zero finite quaternion (w, x, y, z), found {list(wxyz)}")
    out = np.eye(4)
    out[:3, :3] = quat_to_matrix(q).numpy()
    out[:3, 3] = [float(t) for t in translation]
    if not np.isfinite(out).all():
        raise ValueError(f"expected a finite translation (x, y, z), found {list(translation)}")
    return out


def read_rgb(path) -> np.ndarray:
    """uint8 ``[H, W, 3]`` RGB from an image file; InputError naming the file if unreadable."""
    try:
        data = np.fromfile(str(path), np.uint8)
    except OSError:
        data = None
    image = None
    if data is not None and data.size:
        # OpenCV's own warnings about a damaged file would be a second line on stderr: the error says it
        level = cv2.utils.logging.getLogLevel()
        cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)
        try:
            image = cv2.imdecode(data, cv2.IMREAD_COLOR)
        except cv2.error:
            image = None
        finally:
            cv2.utils.logging.setLogLevel(level)
    if image is None or image.ndim != 3:
        found = "no such file" if data is None else "an empty file" if not data.size else "unreadable data"
        raise InputError(f"{path}: expected a readable image file (JPEG/PNG), found {found}")
    return np.ascontiguousarray(image[..., ::-1])


def read_json(path: Path, what: str = "a JSON file"):
    """Parsed JSON of ``path``; InputError naming the file (and the line of a syntax error)."""
    import json

    try:
        return json.loads(Path(path).read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError(f"{path}: expected {what}, found no such file") from None
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(f"{path}: could not read it ({e})") from None
    except json.JSONDecodeError as e:
        raise InputError(f"{path}: expected JSON, found a syntax error at line {e.lineno} column {e.colno} ({e.msg})") from None
