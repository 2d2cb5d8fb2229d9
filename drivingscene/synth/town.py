"""The static town: road layout, road surfaces and markings, buildings, trees, street furniture and
parked cars, all in road-frame coordinates (see ``motion.RoadFrame``)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from drivingscene.synth.meshes import MeshBuilder
from drivingscene.synth.motion import RoadFrame

SIDEWALK_HEIGHT = 0.15  # metres above the carriageway
PAINT_HEIGHT = 0.01
GROUND_HEIGHT = -0.05  # the wide ground plane sits under the roads


@dataclass(frozen=True)
class Layout:
    """Main road (s along, d left) with an optional cross street at ``cross_s``."""

    road: RoadFrame
    lane_width: float
    lanes_per_dir: int
    parking_left: float  # width of the parking strip on the left (0 = none)
    parking_right: float
    sidewalk: float  # sidewalk width, both sides
    cross_s: float | None  # s of the cross street's centre line, None = no intersection
    cross_half: float  # half width of the cross street's carriageway
    s_range: tuple[float, float]  # extent of the town along the road
    cross_range: float  # extent of the cross street on each side (|d|)

    @property
    def half_left(self) -> float:
        return self.lanes_per_dir * self.lane_width + self.parking_left

    @property
    def half_right(self) -> float:
        return self.lanes_per_dir * self.lane_width + self.parking_right

    def half(self, side: int) -> float:
        """Carriageway half width on the left (side = +1) or right (side = -1)."""
        return self.half_left if side > 0 else self.half_right

    def cross_gap(self, margin: float = 0.0) -> tuple[float, float]:
        """s-interval of the cross street including its sidewalks (empty when there is none)."""
        if self.cross_s is None:
            return (np.inf, -np.inf)
        w = self.cross_half + self.sidewalk + margin
        return (self.cross_s - w, self.cross_s + w)

    def in_cross_gap(self, s0: float, s1: float, margin: float = 0.0) -> bool:
        lo, hi = self.cross_gap(margin)
        return s1 > lo and s0 < hi


def sample_layout(rng: np.random.Generator) -> Layout:
    curvature = 0.0 if rng.uniform() < 0.15 else rng.choice([-1, 1]) * rng.uniform(1 / 450, 1 / 160)
    has_cross = rng.uniform() < 0.8
    cross_s = float(rng.choice([-1, 1], p=[0.25, 0.75]) * rng.uniform(16, 42)) if has_cross else None
    return Layout(
        road=RoadFrame(float(curvature)),
        lane_width=float(rng.uniform(3.1, 3.6)),
        lanes_per_dir=int(rng.choice([1, 2], p=[0.55, 0.45])),
        parking_left=float(rng.choice([0.0, 2.3], p=[0.35, 0.65])),
        parking_right=float(rng.choice([0.0, 2.3], p=[0.25, 0.75])),
        sidewalk=float(rng.uniform(3.0, 5.0)),
        cross_s=cross_s,
        cross_half=float(rng.uniform(3.0, 3.6)),
        s_range=(-170.0, 260.0),
        cross_range=120.0,
    )


def strip(b: MeshBuilder, road: RoadFrame, s0, s1, d0, d1, z, material, color, param=0.0, ds=2.0):
    """A horizontal surface over road coordinates [s0, s1] x [d0, d1] at height z; uv = (s, d)."""
    n = max(1, int(np.ceil((s1 - s0) / ds)))
    s = np.linspace(s0, s1, n + 1)
    sa, sb = s[:-1], s[1:]
    corners_sd = np.stack(
        [
            np.stack([sa, np.full(n, d0)], -1),
            np.stack([sb, np.full(n, d0)], -1),
            np.stack([sb, np.full(n, d1)], -1),
            np.stack([sa, np.full(n, d1)], -1),
        ],
        1,
    )
    x, y = road.to_xy(corners_sd[..., 0], corners_sd[..., 1])
    pos = np.stack([x, y, np.full_like(x, z)], -1)[:, [0, 1, 2, 0, 2, 3]].reshape(-1, 3)
    uv = corners_sd[:, [0, 1, 2, 0, 2, 3]].reshape(-1, 2)
    b.add((pos, np.tile([0.0, 0.0, 1.0], (len(pos), 1)), uv), material, color, param)


def wall_along(b, road: RoadFrame, s0, s1, d, z0, z1, facing: int, material, color, ds=2.0):
    """A vertical face at lateral offset d between s0 and s1, facing +d (facing=1) or -d."""
    n = max(1, int(np.ceil((s1 - s0) / ds)))
    s = np.linspace(s0, s1, n + 1)
    x, y = road.to_xy(s, np.full_like(s, d))
    h = road.heading(s)
    nrm = facing * np.stack([-np.sin(h), np.cos(h), 0 * h], -1)
    quad = [(0, z0), (1, z0), (1, z1), (0, z0), (1, z1), (0, z1)]
    pos = np.concatenate([np.stack([x[i : n + i], y[i : n + i], np.full(n, z)], -1)[:, None] for i, z in quad], 1)
    nr = np.concatenate([nrm[i : n + i][:, None] for i, _ in quad], 1)
    uv = np.concatenate([np.stack([s[i : n + i], np.full(n, z)], -1)[:, None] for i, z in quad], 1)
    b.add((pos.reshape(-1, 3), nr.reshape(-1, 3), uv.reshape(-1, 2)), material, color)


def wall_across(b, road: RoadFrame, s, d0, d1, z0, z1, facing: int, material, color):
    """A vertical face along the road normal at s from d0 to d1, facing +s (facing=1) or -s."""
    x, y = road.to_xy(np.array([s, s]), np.array([d0, d1]))
    h = float(road.heading(s))
    nrm = facing * np.array([np.cos(h), np.sin(h), 0.0])
    corners = [(0, z0), (1, z0), (1, z1), (0, z0), (1, z1), (0, z1)]
    pos = np.array([[x[i], y[i], z] for i, z in corners])
    uv = np.array([[[d0, d1][i], z] for i, z in corners])
    b.add((pos, np.tile(nrm, (6, 1)), uv), material, color)


def road_surfaces(b: MeshBuilder, lay: Layout, rng: np.random.Generator) -> None:
    """Carriageways, kerbs, sidewalks and the ground plane."""
    road, (s_lo, s_hi) = lay.road, lay.s_range
    asphalt = np.array([0.30, 0.30, 0.31]) * rng.uniform(0.85, 1.1)
    walk = np.array([0.62, 0.60, 0.56]) * rng.uniform(0.85, 1.05)
    kerb = (0.55, 0.55, 0.53)
    strip(b, road, s_lo, s_hi, -lay.half_right, lay.half_left, 0.0, "asphalt", asphalt, ds=2.0)
    gap_lo, gap_hi = (lay.cross_s - lay.cross_half, lay.cross_s + lay.cross_half) if lay.cross_s is not None else (s_hi, s_hi)
    for side in (1, -1):
        half = lay.half(side)
        for s0, s1 in ((s_lo, gap_lo), (gap_hi, s_hi)):
            if s1 <= s0:
                continue
            d0, d1 = sorted((side * half, side * (half + 0.25)))
            strip(b, road, s0, s1, d0, d1, SIDEWALK_HEIGHT, "kerb", kerb)
            d0, d1 = sorted((side * (half + 0.25), side * (half + lay.sidewalk + 3.0)))
            strip(b, road, s0, s1, d0, d1, SIDEWALK_HEIGHT, "sidewalk", walk, param=0.2)
            wall_along(b, road, s0, s1, side * half, GROUND_HEIGHT, SIDEWALK_HEIGHT, -side, "kerb", kerb)
        if lay.cross_s is not None:
            _cross_surfaces(b, lay, side, asphalt, walk, kerb)
    ground = np.array([0.36, 0.38, 0.26]) * rng.uniform(0.8, 1.1)
    size = 1500.0
    pos = np.array([[-size, -size, 0], [size, -size, 0], [size, size, 0], [-size, -size, 0], [size, size, 0], [-size, size, 0]])
    pos[:, 2] = GROUND_HEIGHT
    b.add((pos, np.tile([0.0, 0.0, 1.0], (6, 1)), pos[:, :2].copy()), "ground", ground)


def _cross_surfaces(b: MeshBuilder, lay: Layout, side: int, asphalt, walk, kerb) -> None:
    """One arm (side = +1 left, -1 right) of the cross street: carriageway, kerbs and sidewalks."""
    road, sx, hw = lay.road, lay.cross_s, lay.cross_half
    half, far = lay.half(side), lay.cross_range
    d0, d1 = sorted((side * half, side * far))
    strip(b, road, sx - hw, sx + hw, d0, d1, 0.0, "asphalt", asphalt, ds=1.0)
    e0, e1 = sorted((side * (half + lay.sidewalk + 3.0), side * far))
    for edge in (-1, 1):
        s_kerb = sx + edge * hw
        s0, s1 = sorted((s_kerb, s_kerb + edge * 0.25))
        strip(b, road, s0, s1, e0, e1, SIDEWALK_HEIGHT, "kerb", kerb, ds=1.0)
        s0, s1 = sorted((s_kerb + edge * 0.25, s_kerb + edge * (lay.sidewalk + 0.25)))
        strip(b, road, s0, s1, e0, e1, SIDEWALK_HEIGHT, "sidewalk", walk, param=0.2, ds=1.0)
        wall_across(b, road, s_kerb, d0, d1, GROUND_HEIGHT, SIDEWALK_HEIGHT, -edge, "kerb", kerb)


def paint_rects(b: MeshBuilder, road: RoadFrame, rects: list[tuple], color, ds: float = 3.0) -> None:
    """Paint rectangles (s0, s1, d0, d1) just above the carriageway."""
    for s0, s1, d0, d1 in rects:
        strip(b, road, s0, s1, d0, d1, PAINT_HEIGHT, "paint", color, ds=ds)


def dashes(s0: float, s1: float, d: float, width: float, dash: float, period: float, phase: float) -> list[tuple]:
    starts = np.arange(s0 + (phase - s0) % period, s1, period)
    return [(a, min(a + dash, s1), d - width / 2, d + width / 2) for a in starts]


def road_markings(b: MeshBuilder, lay: Layout, rng: np.random.Generator) -> None:
    """Centre and lane lines, edge lines, zebra crossings and stop lines."""
    white, yellow = (0.86, 0.86, 0.84), (0.85, 0.68, 0.15)
    s_lo, s_hi = lay.s_range
    pieces = [(s_lo, s_hi)]
    if lay.cross_s is not None:
        lo, hi = lay.cross_s - lay.cross_half - 5.0, lay.cross_s + lay.cross_half + 5.0
        pieces = [(s_lo, lo), (hi, s_hi)]
    lanes, w = lay.lanes_per_dir, lay.lane_width
    phase = rng.uniform(0, 9)
    rects, yellow_rects = [], []
    for s0, s1 in pieces:
        if lanes == 1:
            rects += dashes(s0, s1, 0.0, 0.12, 3.0, 9.0, phase)
        else:
            yellow_rects += [(s0, s1, -0.2, -0.08), (s0, s1, 0.08, 0.2)]
            rects += dashes(s0, s1, w, 0.12, 3.0, 9.0, phase) + dashes(s0, s1, -w, 0.12, 3.0, 9.0, phase)
        for side in (1, -1):
            edge = side * lanes * w if lay.parking_left + lay.parking_right > 0 else side * (lay.half(side) - 0.3)
            rects.append((s0, s1, edge - 0.07, edge + 0.07))
    if lay.cross_s is not None:
        rects += _crossing_marks(lay)
    paint_rects(b, lay.road, rects, white)
    paint_rects(b, lay.road, yellow_rects, yellow)


def _crossing_marks(lay: Layout) -> list[tuple]:
    """Zebra crossings on both approaches, stop lines, and the cross street's centre line."""
    sx, hw, lanes_w = lay.cross_s, lay.cross_half, lay.lanes_per_dir * lay.lane_width
    out = []
    for edge in (-1, 1):
        z0, z1 = sorted((sx + edge * (hw + 1.0), sx + edge * (hw + 4.0)))
        for d in np.arange(-lay.half_right + 0.4, lay.half_left - 0.4, 1.0):
            out.append((z0, z1, d, d + 0.5))
        stop = sx + edge * (hw + 4.6)
        d0, d1 = (-lanes_w, 0.0) if edge < 0 else (0.0, lanes_w)
        out.append((min(stop, stop + edge * 0.4), max(stop, stop + edge * 0.4), d0, d1))
    for side in (1, -1):
        start = lay.half(side) + lay.sidewalk + 2.0
        for a in np.arange(start, lay.cross_range, 9.0):
            d0, d1 = sorted((side * a, side * (a + 3.0)))
            out.append((sx - 0.06, sx + 0.06, d0, d1))
    return out
