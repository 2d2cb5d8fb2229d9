"""A leafy suburban road like DDAD's: a two-lane road with a kerb, grass verges and lawns (a narrow
concrete sidewalk or none), detached houses set back 12-35 m, many trees, bushes and hedges, far
tree lines, utility poles and mailboxes, driveways and few parked cars. Everything is in road-frame
coordinates like the town (``town.Layout``), so the ego, the agents and the ground truth work
unchanged; it draws only from the seed's ``suburb`` stream."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from drivingscene.synth import suburb_lots
from drivingscene.synth.meshes import MeshBuilder
from drivingscene.synth.motion import RoadFrame
from drivingscene.synth.streetscape import Obstacles
from drivingscene.synth.town import GROUND_HEIGHT, SIDEWALK_HEIGHT, Layout, dashes, paint_rects, strip, wall_across, wall_along

SLAB_LIFT = 0.02  # sidewalks and driveways lie this far above the lawn (no depth fighting at 100 m)
LAWN_REACH = 120.0  # lawns reach this far from the centre line; the grass ground plane beyond


@dataclass(frozen=True)
class SuburbLayout(Layout):
    """A ``Layout`` whose roadside is a kerb, a grass verge, an optional sidewalk, then lawns."""

    verge: float = 2.0  # grass between kerb and sidewalk (metres)
    walk: float = 0.0  # sidewalk width (0 = none)
    centre_line: str = "double"  # double (yellow), dashed (yellow), none
    edge_lines: bool = True


def sample_layout(rng: np.random.Generator) -> SuburbLayout:
    curvature = 0.0 if rng.uniform() < 0.3 else rng.choice([-1, 1]) * rng.uniform(1 / 800, 1 / 200)
    verge = float(rng.uniform(1.2, 4.0))
    walk = 0.0 if rng.uniform() < 0.4 else float(rng.uniform(1.2, 1.7))
    cross_s = float(rng.choice([-1, 1], p=[0.3, 0.7]) * rng.uniform(22, 60)) if rng.uniform() < 0.45 else None
    return SuburbLayout(
        road=RoadFrame(float(curvature)),
        lane_width=float(rng.uniform(3.3, 3.8)),
        lanes_per_dir=int(rng.choice([1, 2], p=[0.85, 0.15])),
        parking_left=0.0,
        parking_right=float(rng.choice([0.0, 2.3], p=[0.85, 0.15])),
        sidewalk=verge + walk,  # walkers keep to the verge and the sidewalk
        cross_s=cross_s,
        cross_half=float(rng.uniform(3.0, 3.5)),
        s_range=(-170.0, 260.0),
        cross_range=LAWN_REACH,
        verge=verge,
        walk=walk,
        centre_line=str(rng.choice(["double", "dashed", "none"], p=[0.55, 0.3, 0.15])),
        edge_lines=bool(rng.uniform() < 0.7),
    )


def _surfaces(b: MeshBuilder, lay: SuburbLayout, rng: np.random.Generator) -> None:
    """Asphalt, kerbs, verges, sidewalks and lawns of the main road and the side street."""
    road, (s_lo, s_hi) = lay.road, lay.s_range
    asphalt = np.array([0.34, 0.34, 0.35]) * rng.uniform(0.85, 1.2)
    kerb, concrete = (0.6, 0.6, 0.57), np.array([0.66, 0.65, 0.62]) * rng.uniform(0.9, 1.05)
    lawns = np.array([[0.2, 0.33, 0.1], [0.26, 0.35, 0.13], [0.31, 0.34, 0.17], [0.17, 0.28, 0.1]])  # lush to dry
    lawn = lawns[rng.integers(len(lawns))] * rng.uniform(0.85, 1.15, 3)
    strip(b, road, s_lo, s_hi, -lay.half_right, lay.half_left, 0.0, "asphalt", asphalt, ds=2.0)
    gap = (lay.cross_s - lay.cross_half, lay.cross_s + lay.cross_half) if lay.cross_s is not None else (s_hi, s_hi)
    for side in (1, -1):
        half = lay.half(side)
        for s0, s1 in ((s_lo, gap[0]), (gap[1], s_hi)):
            if s1 <= s0:
                continue
            strip(b, road, s0, s1, *sorted((side * half, side * (half + 0.25))), SIDEWALK_HEIGHT, "kerb", kerb)
            wall_along(b, road, s0, s1, side * half, GROUND_HEIGHT, SIDEWALK_HEIGHT, -side, "kerb", kerb)
            strip(
                b,
                road,
                s0,
                s1,
                *sorted((side * (half + 0.25), side * LAWN_REACH)),
                SIDEWALK_HEIGHT,
                "grass",
                lawn,
                rng.uniform(),
                4.0,
            )
            if lay.walk > 0:
                d0, d1 = sorted((side * (half + lay.verge), side * (half + lay.verge + lay.walk)))
                strip(b, road, s0, s1, d0, d1, SIDEWALK_HEIGHT + SLAB_LIFT, "slab", concrete)
        if lay.cross_s is not None:
            d0, d1 = sorted((side * half, side * LAWN_REACH))
            strip(b, road, gap[0], gap[1], d0, d1, 0.0, "asphalt", asphalt, ds=1.0)
            for edge, s in ((-1, gap[0]), (1, gap[1])):
                wall_across(b, road, s, d0, d1, GROUND_HEIGHT, SIDEWALK_HEIGHT, -edge, "kerb", kerb)
                if lay.walk > 0:
                    s0, s1 = sorted((s + edge * lay.verge, s + edge * (lay.verge + lay.walk)))
                    e0, e1 = sorted((side * (half + lay.verge + lay.walk), side * LAWN_REACH))
                    strip(b, road, s0, s1, e0, e1, SIDEWALK_HEIGHT + SLAB_LIFT, "slab", concrete, ds=1.0)
    size = 1500.0  # grass to the horizon
    pos = np.array([[-size, -size, 0], [size, -size, 0], [size, size, 0], [-size, -size, 0], [size, size, 0], [-size, size, 0]])
    pos[:, 2] = GROUND_HEIGHT
    b.add((pos, np.tile([0.0, 0.0, 1.0], (6, 1)), pos[:, :2].copy()), "grass", lawn * 0.95, 0.3)


def _markings(b: MeshBuilder, lay: SuburbLayout, rng: np.random.Generator) -> None:
    """Yellow centre line (double, dashed or none), white edge and lane lines, stop lines on the side street."""
    white, yellow = (0.86, 0.86, 0.84), (0.85, 0.68, 0.15)
    s_lo, s_hi = lay.s_range
    pieces = [(s_lo, s_hi)]
    if lay.cross_s is not None:
        pieces = [(s_lo, lay.cross_s - lay.cross_half - 1.0), (lay.cross_s + lay.cross_half + 1.0, s_hi)]
    phase = rng.uniform(0, 12)
    rects, yellow_rects = [], []
    for s0, s1 in pieces:
        if lay.centre_line == "double":
            yellow_rects += [(s0, s1, -0.2, -0.08), (s0, s1, 0.08, 0.2)]
        elif lay.centre_line == "dashed":
            yellow_rects += dashes(s0, s1, 0.0, 0.12, 3.0, 12.0, phase)
        if lay.lanes_per_dir == 2:
            rects += dashes(s0, s1, lay.lane_width, 0.12, 3.0, 12.0, phase) + dashes(
                s0, s1, -lay.lane_width, 0.12, 3.0, 12.0, phase
            )
        if lay.edge_lines:
            for side in (1, -1):
                edge = side * lay.lanes_per_dir * lay.lane_width
                rects.append((s0, s1, edge - 0.07, edge + 0.07))
    if lay.cross_s is not None:
        for side in (1, -1):
            d = side * (lay.half(side) + 1.5)
            rects.append((lay.cross_s - lay.cross_half + 0.3, lay.cross_s, *sorted((d, d + side * 0.45))))
    paint_rects(b, lay.road, rects, white)
    paint_rects(b, lay.road, yellow_rects, yellow)


def build_static(lay: SuburbLayout, rng: np.random.Generator) -> tuple[np.ndarray, Obstacles]:
    """Every static mesh of the suburb in road coordinates, and the obstacles moving things avoid."""
    b = MeshBuilder()
    obstacles = Obstacles()
    _surfaces(b, lay, rng)
    _markings(b, lay, rng)
    suburb_lots.roadside(b, lay, rng, obstacles)
    suburb_lots.lots(b, lay, rng, obstacles)
    suburb_lots.tree_lines(b, lay, rng)
    return b.build(), obstacles
