"""Buildings, trees, street furniture and parked cars along the roads of a ``Layout``."""

from __future__ import annotations

import numpy as np

from drivingscene.synth import objects
from drivingscene.synth.meshes import MeshBuilder
from drivingscene.synth.town import SIDEWALK_HEIGHT, Layout

FACADES = {  # material: (probability, palette of wall colours)
    "plaster": (
        0.42,
        [
            (0.82, 0.76, 0.62),
            (0.86, 0.84, 0.78),
            (0.74, 0.62, 0.48),
            (0.70, 0.74, 0.72),
            (0.88, 0.80, 0.58),
            (0.63, 0.50, 0.42),
            (0.78, 0.70, 0.66),
        ],
    ),
    "brick": (0.28, [(0.55, 0.27, 0.18), (0.62, 0.36, 0.24), (0.48, 0.30, 0.24), (0.70, 0.55, 0.40)]),
    "concrete": (0.18, [(0.62, 0.62, 0.60), (0.52, 0.53, 0.54), (0.70, 0.68, 0.63)]),
    "glass_facade": (0.12, [(0.30, 0.42, 0.50), (0.28, 0.36, 0.34), (0.40, 0.44, 0.50)]),
}


class Obstacles:
    """Footprint circles (x, y, radius) of static things, for keeping moving objects clear of them."""

    def __init__(self) -> None:
        self.circles: list[tuple[float, float, float]] = []

    def add(self, x: float, y: float, radius: float) -> None:
        self.circles.append((float(x), float(y), float(radius)))

    def array(self) -> np.ndarray:
        return np.array(self.circles, np.float64).reshape(-1, 3)


def _place(b: MeshBuilder, lay: Layout, verts: np.ndarray, s: float, d: float, yaw: float, z: float = 0.0):
    x, y = lay.road.to_xy(s, d)
    b.add_vertices(objects.moved(verts, float(x), float(y), float(lay.road.heading(s)) + yaw, z))
    return float(x), float(y)


def _building(rng: np.random.Generator) -> np.ndarray:
    names = list(FACADES)
    material = names[rng.choice(len(names), p=[FACADES[n][0] for n in names])]
    palette = FACADES[material][1]
    color = np.array(palette[rng.integers(len(palette))]) * rng.uniform(0.9, 1.08)
    height = rng.uniform(7, 24) if rng.uniform() < 0.85 else rng.uniform(26, 42)
    return material, np.clip(color, 0, 1), height


def buildings(b: MeshBuilder, lay: Layout, rng: np.random.Generator) -> None:
    """Rows of blocks along both sides of the main road and of the cross street."""
    max_len = 24.0 if abs(lay.road.curvature) < 1 / 300 else 17.0
    for side in (1, -1):
        s = lay.s_range[0]
        front = lay.half(side) + lay.sidewalk
        while s < lay.s_range[1]:
            length = rng.uniform(8, max_len)
            if rng.uniform() < 0.15:
                s += rng.uniform(2, 7)
            if lay.in_cross_gap(s, s + length, 0.5):
                s = lay.cross_gap(0.5)[1]
                continue
            depth, setback = rng.uniform(10, 20), rng.uniform(0, 1.5) * (rng.uniform() < 0.4)
            material, color, height = _building(rng)
            verts = objects.building_mesh(length, depth, height, material, color, rng.uniform())
            _place(b, lay, verts, s + length / 2, side * (front + setback + depth / 2), 0.0)
            s += length
        if lay.cross_s is not None:
            _cross_buildings(b, lay, side, rng)
    _vista_ends(b, lay, rng)


def _vista_ends(b: MeshBuilder, lay: Layout, rng: np.random.Generator) -> None:
    """Blocks across the far ends of the streets, so no view runs out onto the empty ground plane."""
    width = lay.half_left + lay.half_right + 2 * lay.sidewalk + 40.0
    for s_end, edge in ((lay.s_range[0], -1), (lay.s_range[1], 1)):
        material, color, height = _building(rng)
        verts = objects.building_mesh(rng.uniform(12, 20), width, max(height, 14.0), material, color, rng.uniform())
        _place(b, lay, verts, s_end + edge * 10.0, (lay.half_left - lay.half_right) / 2, 0.0)
    if lay.cross_s is None:
        return
    for side in (1, -1):
        material, color, height = _building(rng)
        verts = objects.building_mesh(
            2 * (lay.cross_half + lay.sidewalk) + 30.0, rng.uniform(12, 20), max(height, 14.0), material, color, rng.uniform()
        )
        _place(b, lay, verts, lay.cross_s, side * (lay.cross_range + 8.0), 0.0)


def _cross_buildings(b: MeshBuilder, lay: Layout, side: int, rng: np.random.Generator) -> None:
    """Blocks facing the cross street on one of its arms (side = +1 left of the main road)."""
    for edge in (-1, 1):
        d = lay.half(side) + lay.sidewalk + 21.0
        front = lay.cross_half + lay.sidewalk
        while d < lay.cross_range - 5:
            length = rng.uniform(8, 20)
            depth = rng.uniform(10, 18)
            material, color, height = _building(rng)
            verts = objects.building_mesh(length, depth, height, material, color, rng.uniform())
            s_c = lay.cross_s + edge * (front + depth / 2)
            _place(b, lay, verts, s_c, side * (d + length / 2), np.pi / 2)
            d += length + rng.uniform(0, 3) * (rng.uniform() < 0.2)


def trees_and_furniture(b: MeshBuilder, lay: Layout, rng: np.random.Generator, obstacles: Obstacles) -> None:
    """Street trees, lamps and signs on the sidewalks; traffic lights at the intersection."""
    for side in (1, -1):
        kerb = lay.half(side)
        if rng.uniform() < 0.75:
            s = lay.s_range[0] + rng.uniform(0, 10)
            spacing = rng.uniform(9, 16)
            while s < lay.s_range[1]:
                if not lay.in_cross_gap(s - 2, s + 2, 1.0):
                    xy = _place(b, lay, objects.tree_mesh(rng, rng.uniform()), s, side * (kerb + 1.2), 0.0, SIDEWALK_HEIGHT)
                    obstacles.add(*xy, 0.5)
                s += spacing * rng.uniform(0.8, 1.2)
        s = lay.s_range[0] + rng.uniform(0, 30)
        lamp = objects.streetlamp_mesh(rng.uniform(6.5, 8.0), rng.uniform(1.2, 2.2), rng.uniform())
        while s < lay.s_range[1]:
            if not lay.in_cross_gap(s - 1, s + 1, 1.0):
                xy = _place(b, lay, lamp, s + 5.5, side * (kerb + 0.45), 0.0 if side < 0 else np.pi, SIDEWALK_HEIGHT)
                obstacles.add(*xy, 0.3)
            s += 32.0
        for _ in range(int(rng.integers(1, 4))):
            s = rng.uniform(-40, 80)
            if not lay.in_cross_gap(s - 1, s + 1, 1.0):
                color = [(0.85, 0.85, 0.85), (0.1, 0.25, 0.65), (0.75, 0.1, 0.08)][rng.integers(3)]
                xy = _place(
                    b,
                    lay,
                    objects.sign_mesh(rng.uniform(), color),
                    s,
                    side * (kerb + 0.4),
                    np.pi if side > 0 else 0.0,
                    SIDEWALK_HEIGHT,
                )
                obstacles.add(*xy, 0.3)
    if lay.cross_s is not None:
        _traffic_lights(b, lay, rng, obstacles)


def _traffic_lights(b: MeshBuilder, lay: Layout, rng: np.random.Generator, obstacles: Obstacles) -> None:
    state = int(rng.integers(3))
    for edge, side in ((-1, -1), (1, 1)):
        s = lay.cross_s + edge * (lay.cross_half + 0.8)
        yaw = np.pi if edge < 0 else 0.0  # faces traffic approaching the intersection
        xy = _place(
            b, lay, objects.traffic_light_mesh(rng.uniform(), state), s, side * (lay.half(side) + 0.5), yaw, SIDEWALK_HEIGHT
        )
        obstacles.add(*xy, 0.3)


def parked_cars(b: MeshBuilder, lay: Layout, rng: np.random.Generator, obstacles: Obstacles) -> None:
    """Cars parked along the kerbs (parking strips only), with gaps."""
    kinds, probs = ["sedan", "hatchback", "suv", "van"], [0.4, 0.27, 0.23, 0.1]
    for side, width in ((1, lay.parking_left), (-1, lay.parking_right)):
        if width <= 0:
            continue
        d = side * (lay.lanes_per_dir * lay.lane_width + width / 2 + 0.05)
        s = lay.s_range[0] + rng.uniform(0, 5)
        occupancy = rng.uniform(0.45, 0.85)
        while s < min(lay.s_range[1], 150):
            kind = kinds[rng.choice(len(kinds), p=probs)]
            length = objects.VEHICLES[kind].length
            if rng.uniform() < occupancy and not lay.in_cross_gap(s - 6, s + length + 6, 0.0):
                color = np.clip(objects.CAR_COLOURS[rng.integers(len(objects.CAR_COLOURS))] * rng.uniform(0.85, 1.1), 0, 1)
                verts = objects.vehicle_mesh(kind, color, rng.uniform())
                xy = _place(b, lay, verts, s + length / 2, d, 0.0 if side < 0 else np.pi)
                obstacles.add(*xy, length / 2)
            s += length + rng.uniform(0.6, 3.0)
