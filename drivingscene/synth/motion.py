"""Exact poses as functions of time: constant-curvature paths, the road frame and moving agents.

Everything moves in the ground plane of the *road frame* (x along the main road at s = 0, y left,
z up); ``road_to_world`` places the road frame in the world with an offset and a yaw, so the world
origin is far from the ego. A path is a chain of constant-curvature pieces (lines and arcs) and a
pose at distance u along it is closed-form, so every pose at every time is exact.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def arc_offset(u: np.ndarray, curvature: float) -> tuple[np.ndarray, np.ndarray]:
    """Local (forward, left) displacement after driving ``u`` metres with constant curvature.

    ``sin(k u) / k`` and ``(1 - cos(k u)) / k`` written with sinc so that k = 0 is exact.
    """
    u = np.asarray(u, dtype=np.float64)
    half = curvature * u / 2
    forward = u * np.sinc(curvature * u / np.pi)
    left = u * np.sin(half) * np.sinc(half / np.pi)
    return forward, left


@dataclass(frozen=True)
class Path:
    """A chain of constant-curvature pieces starting at (x0, y0) with ``heading0`` (radians, road frame).

    Distances before 0 or after the end extend the first or last piece.
    """

    x0: float
    y0: float
    heading0: float
    pieces: tuple[tuple[float, float], ...]  # (length in metres, curvature in 1/m)

    def _piece_starts(self) -> list[tuple[float, float, float, float]]:
        """(distance, x, y, heading) at the start of each piece."""
        out, dist, x, y, h = [], 0.0, self.x0, self.y0, self.heading0
        for length, curv in self.pieces:
            out.append((dist, x, y, h))
            fwd, left = arc_offset(length, curv)
            x, y = x + fwd * np.cos(h) - left * np.sin(h), y + fwd * np.sin(h) + left * np.cos(h)
            h, dist = h + curv * length, dist + length
        return out

    def pose(self, u: float) -> tuple[float, float, float]:
        """(x, y, heading) after ``u`` metres along the path."""
        starts = self._piece_starts()
        idx = 0
        for i, (dist, *_rest) in enumerate(starts):
            if u >= dist:
                idx = i
        dist, x, y, h = starts[idx]
        curv = self.pieces[idx][1]
        fwd, left = (float(a) for a in arc_offset(u - dist, curv))
        return x + fwd * np.cos(h) - left * np.sin(h), y + fwd * np.sin(h) + left * np.cos(h), h + curv * (u - dist)

    @property
    def length(self) -> float:
        return float(sum(p[0] for p in self.pieces))


def planar_pose(x: float, y: float, heading: float, z: float = 0.0) -> np.ndarray:
    """``[4, 4]`` float64 pose of a z-up body at (x, y, z) facing ``heading``."""
    c, s = np.cos(heading), np.sin(heading)
    out = np.eye(4)
    out[:2, :2] = [[c, -s], [s, c]]
    out[:3, 3] = (x, y, z)
    return out


@dataclass(frozen=True)
class RoadFrame:
    """The main road's centre line: an arc of ``curvature`` through the road-frame origin along +x.

    ``to_xy(s, d)`` maps road coordinates (s along the centre line, d to the left) to the road
    frame's plane; the cross street and everything else are laid out in these coordinates.
    """

    curvature: float

    def heading(self, s: np.ndarray) -> np.ndarray:
        return self.curvature * np.asarray(s, dtype=np.float64)

    def to_xy(self, s: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        fwd, left = arc_offset(s, self.curvature)
        h = self.heading(s)
        return fwd - np.asarray(d) * np.sin(h), left + np.asarray(d) * np.cos(h)

    def to_sd(self, x: float, y: float) -> tuple[float, float]:
        """Inverse of ``to_xy`` (within half a turn of the origin)."""
        if abs(self.curvature) < 1e-12:
            return float(x), float(y)
        radius = 1.0 / self.curvature
        sign = np.sign(radius)
        theta = np.arctan2(sign * x, sign * (radius - y))
        return float(theta / self.curvature), float(radius - sign * np.hypot(x, y - radius))

    def lane_path(self, d: float, s_start: float, forward: bool = True) -> Path:
        """The path along the lane at lateral offset ``d``, starting at ``s_start``, either direction."""
        x, y = self.to_xy(s_start, d)
        h = float(self.heading(s_start))
        curv = self.curvature / (1.0 - self.curvature * d)  # a circle of radius 1/k - d
        if forward:
            return Path(float(x), float(y), h, ((1e4, curv),))
        return Path(float(x), float(y), h + np.pi, ((1e4, -curv),))

    def radial_path(self, s: float, d_start: float, outward_left: bool) -> Path:
        """A straight path along the road normal at ``s`` (the cross street), from offset ``d_start``."""
        x, y = self.to_xy(s, d_start)
        h = float(self.heading(s)) + (np.pi / 2 if outward_left else -np.pi / 2)
        return Path(float(x), float(y), h, ((1e4, 0.0),))


@dataclass(frozen=True)
class Mover:
    """Something that drives along a path at constant speed: ``u(t) = u0 + speed * (t - t_ref)``."""

    path: Path
    speed: float  # m/s
    u0: float  # metres along the path at t_ref
    t_ref: float  # seconds

    def road_pose(self, t: float) -> np.ndarray:
        """``[4, 4]`` body-to-road-frame pose at time ``t`` (seconds)."""
        x, y, h = self.path.pose(self.u0 + self.speed * (t - self.t_ref))
        return planar_pose(x, y, h)

    def position(self, t: float) -> np.ndarray:
        x, y, _ = self.path.pose(self.u0 + self.speed * (t - self.t_ref))
        return np.array([x, y])
