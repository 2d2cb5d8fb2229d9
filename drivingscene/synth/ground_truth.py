"""Ground truth from the geometry pass: depth, optical flow, scene flow and the dynamic mask.

Definitions (per keyframe k, camera v, pixel centre p = (u, v)):

- ``gt_depth``: camera z of the surface point X seen at p at time t_k; 0 for sky.
- ``gt_flow``: project(X at time t_other, in the same camera at t_other) - p. X moves with its
  object, the camera with the ego. Points hidden at t_other still get this geometric flow. For sky
  pixels X is the point at infinity along the ray, so the flow is the camera's pure-rotation flow.
  If X lies behind the camera at t_other (z <= MIN_Z) it is projected with z clamped to MIN_Z:
  finite but far outside the image, and such pixels fail every forward-backward check.
- ``gt_scene_flow``: world position of X at t_other minus at t_k (metres); exactly 0 for the
  static town and for sky.
- ``gt_dynamic``: X belongs to an independently moving object (vehicle or pedestrian).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

MIN_Z = 1e-3  # metres


@dataclass(frozen=True, eq=False)
class KeyframeTruth:
    depth: np.ndarray  # [V, H, W] float32
    flow: np.ndarray  # [V, H, W, 2] float32
    scene_flow: np.ndarray  # [V, H, W, 3] float32
    dynamic: np.ndarray  # [V, H, W] bool


def pixel_rays(intrinsics: np.ndarray, height: int, width: int) -> np.ndarray:
    """Camera-frame rays ``[V, H, W, 3]`` (z = 1) through the pixel centres."""
    k = np.asarray(intrinsics, np.float64)[:, None, None]
    v, u = np.meshgrid(np.arange(height, dtype=np.float64), np.arange(width, dtype=np.float64), indexing="ij")
    y = (v - k[..., 1, 2]) / k[..., 1, 1]
    x = (u - k[..., 0, 2] - k[..., 0, 1] * y) / k[..., 0, 0]
    return np.stack([x, y, np.ones_like(x)], -1)


def project_points(points: np.ndarray, intrinsics: np.ndarray) -> np.ndarray:
    """Camera points ``[V, H, W, 3]`` to pixels ``[V, H, W, 2]``; z clamped to ``MIN_Z``."""
    k = np.asarray(intrinsics, np.float64)[:, None, None]
    z = np.maximum(points[..., 2], MIN_Z)
    x, y = points[..., 0] / z, points[..., 1] / z
    return np.stack([k[..., 0, 0] * x + k[..., 0, 1] * y + k[..., 0, 2], k[..., 1, 1] * y + k[..., 1, 2]], -1)


def keyframe_truth(
    now: np.ndarray,  # [V, H, W, 4] camera point now, dynamic flag
    other: np.ndarray,  # [V, H, W, 4] camera point at the other keyframe (same camera), coverage
    displacement: np.ndarray,  # [V, H, W, 4] world displacement, object id
    intrinsics: np.ndarray,  # [V, 3, 3]
    cams_now_to_world: np.ndarray,  # [V, 4, 4]
    cams_other_to_world: np.ndarray,  # [V, 4, 4]
) -> KeyframeTruth:
    """Depth, flow, scene flow and dynamic mask of one keyframe from the geometry-pass buffers."""
    views, height, width = now.shape[:3]
    covered = other[..., 3] > 0.5
    rays = pixel_rays(intrinsics, height, width)
    now_to_other = np.einsum("vij,vjk->vik", np.linalg.inv(cams_other_to_world)[:, :3, :3], cams_now_to_world[:, :3, :3])
    at_infinity = (rays.reshape(views, -1, 3) @ now_to_other.transpose(0, 2, 1)).reshape(rays.shape)
    target = np.where(covered[..., None], other[..., :3].astype(np.float64), at_infinity)
    grid = np.stack(np.meshgrid(np.arange(width), np.arange(height), indexing="xy"), -1).astype(np.float64)
    flow = project_points(target, intrinsics) - grid
    depth = np.where(covered, now[..., 2], 0.0)
    scene_flow = np.where(covered[..., None], displacement[..., :3], 0.0)
    dynamic = covered & (now[..., 3] > 0.5)
    return KeyframeTruth(depth.astype(np.float32), flow.astype(np.float32), scene_flow.astype(np.float32), dynamic)
