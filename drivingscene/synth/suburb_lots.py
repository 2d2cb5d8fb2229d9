"""What stands along a suburban road: lots with houses, driveways, yard trees, bushes and hedges;
roadside trees, poles, lamps, signs, mailboxes and a few parked cars; woodland behind the lots and
at the ends of the streets. Lots are laid out along ``Frontage`` lines (the main road's two sides
and the side street's four), in road coordinates."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from drivingscene.synth import objects, suburb_objects
from drivingscene.synth.meshes import MeshBuilder
from drivingscene.synth.streetscape import Obstacles
from drivingscene.synth.town import SIDEWALK_HEIGHT, Layout, strip

LIFT = 0.02  # driveways above the lawn, as sidewalks


@dataclass(frozen=True)
class Frontage:
    """A street edge: ``u`` runs along it (road s for the main road, |d| for the side street) and
    ``w`` away from its kerb line. ``yaw`` turns an object's -y toward the street."""

    lay: Layout
    side: int  # +1 left of the main road, -1 right
    edge: int = 0  # 0: the main road; -1 / +1: the side street's edge at smaller / larger s

    def sd(self, u: float, w: float) -> tuple[float, float]:
        lay = self.lay
        if self.edge == 0:
            return u, self.side * (lay.half(self.side) + w)
        return lay.cross_s + self.edge * (lay.cross_half + w), self.side * u

    @property
    def yaw(self) -> float:
        if self.edge == 0:
            return 0.0 if self.side > 0 else np.pi
        return -self.edge * np.pi / 2

    @property
    def x_sign(self) -> int:
        """+1 if an object's x axis runs along +u."""
        if self.edge == 0:
            return self.side
        return -self.edge * self.side

    def place(self, b: MeshBuilder, verts: np.ndarray, u: float, w: float, yaw: float = 0.0, z: float = SIDEWALK_HEIGHT):
        s, d = self.sd(u, w)
        x, y = self.lay.road.to_xy(s, d)
        b.add_vertices(objects.moved(verts, float(x), float(y), float(self.lay.road.heading(s)) + self.yaw + yaw, z))
        return float(x), float(y)

    def rect(self, b: MeshBuilder, u0, u1, w0, w1, z, material, color) -> None:
        (s0, d0), (s1, d1) = self.sd(u0, w0), self.sd(u1, w1)
        strip(b, self.lay.road, min(s0, s1), max(s0, s1), min(d0, d1), max(d0, d1), z, material, color, ds=3.0)


def random_tree(rng: np.random.Generator, low: float = 4.0, high: float = 18.0) -> np.ndarray:
    """A broadleaf tree (80 %) or a conifer between ``low`` and ``high`` metres tall."""
    return suburb_objects.plant(rng, "conifer" if rng.uniform() < 0.2 else "broadleaf", rng.uniform(low, high))


def random_bush(rng: np.random.Generator, length: tuple, width: tuple, height: tuple) -> np.ndarray:
    return suburb_objects.plant(rng, "bush", (rng.uniform(*length), rng.uniform(*width), rng.uniform(*height)))


def _frontages(lay: Layout) -> list[tuple[Frontage, float, float, tuple[float, float]]]:
    """Each frontage with its u range and the u interval it leaves free (the side street)."""
    out = []
    for side in (1, -1):
        free = (np.inf, -np.inf)
        if lay.cross_s is not None:
            free = (lay.cross_s - lay.cross_half - 40.0, lay.cross_s + lay.cross_half + 40.0)
        out.append((Frontage(lay, side), *lay.s_range, free))
        if lay.cross_s is not None:
            for edge in (-1, 1):
                out.append((Frontage(lay, side, edge), lay.half(side) + 12.0, lay.cross_range - 10.0, (np.inf, -np.inf)))
    return out


def _garage_u(verts: np.ndarray, length: float, front: Frontage, u: float, rng) -> float:
    """u of the driveway: in front of the garage door the shader draws (or a random end)."""
    param = float(verts[0, 12])
    if (param * 17.3) % 1.0 >= 0.6 and length / 2 >= 4.5:
        return u + front.x_sign * np.sign((param * 2.9) % 1.0 - 0.5) * (length / 2 - 2.0)
    return u + rng.choice([-1, 1]) * (length / 2 - 1.5)


def _house_lot(b, front: Frontage, u: float, width: float, rng, obstacles: Obstacles, setback: tuple) -> None:
    length, depth = min(width - rng.uniform(4, 8), rng.uniform(9, 17)), rng.uniform(7.5, 12)
    w_front = rng.uniform(*setback)
    house = suburb_objects.house_mesh(rng, length, depth)
    front.place(b, house, u, w_front + depth / 2)
    drive_u = _garage_u(house, length, front, u, rng)
    drive_w = rng.uniform(3.0, 5.0)
    front.rect(b, drive_u - drive_w / 2, drive_u + drive_w / 2, 0.25, w_front, SIDEWALK_HEIGHT + LIFT, "slab", (0.64, 0.63, 0.6))
    if rng.uniform() < 0.35:
        color = np.clip(objects.CAR_COLOURS[rng.integers(len(objects.CAR_COLOURS))] * rng.uniform(0.85, 1.1), 0, 1)
        kind = ["sedan", "hatchback", "suv", "van"][rng.integers(4)]
        car = objects.vehicle_mesh(kind, color, rng.uniform())
        front.place(b, car, drive_u, w_front - 3.2, -np.pi / 2 + rng.choice([0.0, np.pi]), SIDEWALK_HEIGHT + LIFT)
    if rng.uniform() < 0.6:
        xy = front.place(b, suburb_objects.mailbox_mesh(rng, rng.uniform()), drive_u + drive_w / 2 + 0.8, 0.7)
        obstacles.add(*xy, 0.3)
    for _ in range(int(rng.integers(2, 6))):  # foundation planting
        du = rng.uniform(-length / 2, length / 2)
        if abs(u + du - drive_u) > drive_w / 2 + 1.0:
            front.place(b, random_bush(rng, (0.8, 2.2), (0.7, 1.3), (0.6, 1.4)), u + du, w_front - 0.7)
    _yard_trees(b, front, u, width, w_front, depth, drive_u, rng)
    if rng.uniform() < 0.2:  # a hedge along one lot boundary
        edge_u = u + rng.choice([-1, 1]) * width / 2
        hedge = random_bush(rng, (6.0, 16.0), (0.7, 1.1), (1.0, 2.0))
        front.place(b, hedge, edge_u, w_front + rng.uniform(-4, 4), np.pi / 2)


def _yard_trees(b, front: Frontage, u: float, width: float, w_front: float, depth: float, drive_u: float, rng) -> None:
    """0-2 trees in the front yard, 1-4 beside and behind the house."""
    walk_end = front.lay.verge + front.lay.walk + 2.0
    for _ in range(int(rng.integers(0, 3))):
        if w_front - 3.0 > walk_end:
            tu = u + rng.uniform(-width / 2, width / 2)
            if abs(tu - drive_u) > 3.5:
                front.place(b, random_tree(rng), tu, rng.uniform(walk_end, w_front - 3.0))
    for _ in range(int(rng.integers(1, 5))):
        tu = u + rng.choice([-1, 1]) * rng.uniform(0.35, 0.5) * width
        front.place(b, random_tree(rng, 8.0, 22.0), tu, w_front + rng.uniform(0, depth + 14))


def _empty_lot(b, front: Frontage, u: float, width: float, rng) -> None:
    """A lawn with a copse of trees and some shrubs, or a stand of woodland."""
    walk_end = front.lay.verge + front.lay.walk + 3.0
    for _ in range(int(rng.integers(2, 8))):
        front.place(b, random_tree(rng), u + rng.uniform(-width / 2, width / 2), rng.uniform(walk_end + 3.0, 45.0))
    if rng.uniform() < 0.5:  # dense woodland down to the ground, close to the road
        for _ in range(int(rng.integers(2, 5))):
            mass = suburb_objects.plant(rng, "mass", rng.uniform(10, 20))
            front.place(b, mass, u + rng.uniform(-width / 2, width / 2), rng.uniform(walk_end + 6.0, 40.0), 0.0, 0.0)
    for _ in range(int(rng.integers(0, 4))):
        bush = random_bush(rng, (1.0, 3.0), (0.8, 1.6), (0.7, 1.6))
        front.place(b, bush, u + rng.uniform(-width / 2, width / 2), rng.uniform(walk_end, 30.0))


def lots(b: MeshBuilder, lay: Layout, rng: np.random.Generator, obstacles: Obstacles) -> None:
    """Lots 18-32 m wide along every frontage: a house (85 %, on some streets 50 %) or trees."""
    for front, u_lo, u_hi, free in _frontages(lay):
        setback = (12.0, 35.0) if front.edge == 0 else (10.0, 22.0)
        houses = 0.85 if rng.uniform() < 0.7 else 0.5  # some streets run past woods and open lots
        u = u_lo + rng.uniform(0, 10)
        while u < u_hi:
            width = rng.uniform(18, 32)
            centre = u + width / 2
            if not (free[0] < centre + width / 2 and centre - width / 2 < free[1]):
                if rng.uniform() < houses:
                    _house_lot(b, front, centre, width, rng, obstacles, setback)
                else:
                    _empty_lot(b, front, centre, width, rng)
            u += width


def _along(rng: np.random.Generator, lay: Layout, spacing: tuple[float, float], margin: float):
    """s positions from one end of the road to the other, skipping the side street."""
    s = lay.s_range[0] + rng.uniform(0, spacing[1])
    while s < lay.s_range[1]:
        if not lay.in_cross_gap(s - margin, s + margin, 1.0):
            yield float(s)
        s += rng.uniform(*spacing)


def roadside(b: MeshBuilder, lay, rng: np.random.Generator, obstacles: Obstacles) -> None:
    """Verge trees, utility poles, street lamps, signs, hydrants and a few cars at the kerb."""
    for side in (1, -1):
        front = Frontage(lay, side)
        if rng.uniform() < 0.7:  # big trees near the road: in a wide verge, else just behind it
            w = 0.25 + lay.verge / 2 if lay.verge >= 2.2 else lay.verge + lay.walk + rng.uniform(1.5, 4.0)
            for s in _along(rng, lay, (8.0, 22.0), 2.0):
                obstacles.add(*front.place(b, random_tree(rng, 10.0, 24.0), s, w + rng.uniform(-0.3, 0.3)), 0.5)
        if rng.uniform() < 0.4:
            lamp = objects.streetlamp_mesh(rng.uniform(6.5, 8.5), rng.uniform(1.0, 2.0), rng.uniform())
            for s in _along(rng, lay, (40.0, 60.0), 1.0):
                obstacles.add(*front.place(b, lamp, s, 0.6, np.pi), 0.3)  # the arm (+y) reaches over the road
        for _ in range(int(rng.integers(0, 3))):
            s = rng.uniform(-40, 90)
            if not lay.in_cross_gap(s - 1, s + 1, 1.0):
                color = [(0.88, 0.88, 0.86), (0.85, 0.7, 0.1), (0.1, 0.42, 0.2)][rng.integers(3)]
                obstacles.add(*front.place(b, objects.sign_mesh(rng.uniform(), color), s, 0.5, -np.pi / 2), 0.3)
        if rng.uniform() < 0.5:
            s = rng.uniform(-30, 80)
            if not lay.in_cross_gap(s - 1, s + 1, 1.0):
                obstacles.add(*front.place(b, suburb_objects.hydrant_mesh(rng.uniform()), s, 0.7), 0.3)
    pole_side = int(rng.choice([-1, 1]))
    if rng.uniform() < 0.75:
        pole_front, w = Frontage(lay, pole_side), (lay.verge - 0.5 if lay.walk == 0 else lay.verge + lay.walk + 0.8)
        for s in _along(rng, lay, (35.0, 50.0), 1.0):
            obstacles.add(*pole_front.place(b, suburb_objects.utility_pole_mesh(rng, rng.uniform()), s, w), 0.3)
    _kerb_cars(b, lay, rng, obstacles)


def _kerb_cars(b: MeshBuilder, lay, rng: np.random.Generator, obstacles: Obstacles) -> None:
    """A sparse row of cars on the parking strip, if the road has one."""
    if lay.parking_right <= 0:
        return
    d = -(lay.lanes_per_dir * lay.lane_width + lay.parking_right / 2 + 0.05)
    for s in _along(rng, lay, (14.0, 40.0), 8.0):
        if s < 150 and rng.uniform() < 0.35:
            kind = ["sedan", "hatchback", "suv"][rng.integers(3)]
            color = np.clip(objects.CAR_COLOURS[rng.integers(len(objects.CAR_COLOURS))] * rng.uniform(0.85, 1.1), 0, 1)
            x, y = lay.road.to_xy(s, d)
            b.add_vertices(
                objects.moved(objects.vehicle_mesh(kind, color, rng.uniform()), float(x), float(y), float(lay.road.heading(s)))
            )
            obstacles.add(float(x), float(y), objects.VEHICLES[kind].length / 2)


def tree_lines(b: MeshBuilder, lay, rng: np.random.Generator) -> None:
    """Woodland behind the lots on both sides, and across the far ends of the streets."""
    for side in (1, -1):
        front = Frontage(lay, side)
        for s in _along(rng, lay, (7.0, 11.0), 6.0):
            for row in range(1 + int(rng.uniform() < 0.35)):
                mass = suburb_objects.plant(rng, "mass", rng.uniform(12, 22))
                front.place(b, mass, s + rng.uniform(-3, 3), rng.uniform(55, 70) + 12.0 * row, 0.0, 0.0)
    for s_end, edge in ((lay.s_range[0], -1), (lay.s_range[1], 1)):
        for d in np.arange(-70.0, 70.0, rng.uniform(7, 10)):
            mass = suburb_objects.plant(rng, "mass", rng.uniform(12, 20))
            x, y = lay.road.to_xy(s_end + edge * rng.uniform(12, 25), d)
            b.add_vertices(objects.moved(mass, float(x), float(y), 0.0))
    if lay.cross_s is None:
        return
    for side in (1, -1):
        for ds in np.arange(-40.0, 40.0, rng.uniform(7, 10)):
            mass = suburb_objects.plant(rng, "mass", rng.uniform(12, 20))
            x, y = lay.road.to_xy(lay.cross_s + ds, side * (lay.cross_range + rng.uniform(5, 15)))
            b.add_vertices(objects.moved(mass, float(x), float(y), 0.0))
