"""Selection masks from screen-space shapes and world spheres (positions at the current time).

Rectangle and brush select every Gaussian whose centre projects inside the shape (in front of the
camera), occluded or not, like SuperSplat; the sphere selects by world distance from a picked point.
"""

from __future__ import annotations

import numpy as np
from drivingscene_view.camera import ViewCamera

NEAR = 0.01


def rect_mask(points: np.ndarray, camera: ViewCamera, rect: tuple[float, float, float, float]) -> np.ndarray:
    """``[N]`` bool: centres ``[N, 3]`` projecting into (u0, v0, u1, v1) pixels (any corner order)."""
    uv, z = camera.project(points)
    u0, u1 = sorted((rect[0], rect[2]))
    v0, v1 = sorted((rect[1], rect[3]))
    return (z > NEAR) & (uv[:, 0] >= u0) & (uv[:, 0] <= u1) & (uv[:, 1] >= v0) & (uv[:, 1] <= v1)


def brush_mask(points: np.ndarray, camera: ViewCamera, centre: tuple[float, float], radius: float) -> np.ndarray:
    """``[N]`` bool: centres within ``radius`` pixels of ``centre`` on screen."""
    uv, z = camera.project(points)
    d2 = (uv[:, 0] - centre[0]) ** 2 + (uv[:, 1] - centre[1]) ** 2
    return (z > NEAR) & (d2 <= radius * radius)


def sphere_mask(points: np.ndarray, centre: np.ndarray, radius: float) -> np.ndarray:
    """``[N]`` bool: centres within ``radius`` metres of ``centre``."""
    return ((points - np.asarray(centre, points.dtype)) ** 2).sum(axis=1) <= radius * radius


def pick(
    points: np.ndarray, camera: ViewCamera, pixel: tuple[float, float], candidates: np.ndarray, tolerance: float = 6.0
) -> int | None:
    """Index of the nearest-to-camera Gaussian among ``candidates`` (bool ``[N]``) whose centre projects
    within ``tolerance`` pixels of ``pixel``; None if there is none."""
    uv, z = camera.project(points)
    d2 = (uv[:, 0] - pixel[0]) ** 2 + (uv[:, 1] - pixel[1]) ** 2
    ok = candidates & (z > NEAR) & (d2 <= tolerance * tolerance)
    if not ok.any():
        return None
    index = np.flatnonzero(ok)
    return int(index[np.argmin(z[index])])
