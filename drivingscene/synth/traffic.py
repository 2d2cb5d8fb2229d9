"""Moving agents: vehicles following, oncoming, crossing and turning at the intersection, and
pedestrians walking along sidewalks or over the zebra crossing. Each has an exact pose function of
time (a ``Mover``) and is kept clear of the ego, other agents and static obstacles."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from drivingscene.synth import objects
from drivingscene.synth.motion import Mover, Path
from drivingscene.synth.streetscape import Obstacles
from drivingscene.synth.town import SIDEWALK_HEIGHT, Layout

KINDS = ("follow", "oncoming", "crossing", "turning", "walker", "zebra")
WEIGHTS = (3.0, 3.0, 2.0, 1.5, 2.5, 1.0)


@dataclass(frozen=True, eq=False)
class Agent:
    """A rigid moving object: its mesh in its own frame, and how it moves."""

    kind: str  # one of KINDS
    mover: Mover
    vertices: np.ndarray  # [N, VERTEX_FLOATS] object frame
    z: float  # height of the object frame above the road plane
    circles: np.ndarray  # [C, 3] footprint circles (x forward, y left, radius) in the object frame

    def road_pose(self, t: float) -> np.ndarray:
        """``[4, 4]`` object-to-road-frame pose at time t (seconds)."""
        pose = self.mover.road_pose(t)
        pose[2, 3] = self.z
        return pose


def vehicle_circles(kind: str) -> np.ndarray:
    v = objects.VEHICLES[kind]
    n = max(2, int(np.ceil(v.length / v.width)))
    xs = np.linspace(-v.length / 2 + v.width / 2, v.length / 2 - v.width / 2, n)
    return np.stack([xs, np.zeros(n), np.full(n, v.width / 2 + 0.25)], -1)


def world_circles(circles: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """Footprint circles ``[C, 3]`` moved by a ``[4, 4]`` pose into the road plane."""
    xy = circles[:, :2] @ pose[:2, :2].T + pose[:2, 3]
    return np.concatenate([xy, circles[:, 2:]], -1)


def _vehicle(rng: np.random.Generator) -> tuple[str, np.ndarray]:
    kind = ["sedan", "hatchback", "suv", "van", "bus"][rng.choice(5, p=[0.36, 0.24, 0.22, 0.12, 0.06])]
    color = np.clip(objects.CAR_COLOURS[rng.integers(len(objects.CAR_COLOURS))] * rng.uniform(0.85, 1.1), 0, 1)
    return kind, objects.vehicle_mesh(kind, color, rng.uniform())


def _lane_vehicle(lay: Layout, rng, t0: float, speed_scale: float, oncoming: bool) -> Agent:
    lane = int(rng.integers(lay.lanes_per_dir))
    d = (lane + 0.5) * lay.lane_width * (1 if oncoming else -1)
    s = rng.uniform(-25, 60) if oncoming else rng.choice([-1, 1], p=[0.35, 0.65]) * rng.uniform(7, 40)
    kind, verts = _vehicle(rng)
    speed = rng.uniform(5, 13) * speed_scale
    return Agent(
        "oncoming" if oncoming else "follow",
        Mover(lay.road.lane_path(d, s, not oncoming), speed, 0.0, t0),
        verts,
        0.0,
        vehicle_circles(kind),
    )


def _crossing_vehicle(lay: Layout, rng, t0: float, speed_scale: float) -> Agent:
    direction = int(rng.choice([-1, 1]))
    lane_s = lay.cross_s + direction * lay.cross_half / 2  # right-hand traffic
    d = rng.uniform(-45, 45)
    kind, verts = _vehicle(rng)
    path = lay.road.radial_path(lane_s, d, direction > 0)
    return Agent("crossing", Mover(path, rng.uniform(4, 11) * speed_scale, 0.0, t0), verts, 0.0, vehicle_circles(kind))


def _turning_vehicle(lay: Layout, rng, t0: float, speed_scale: float) -> Agent:
    """Approach along a main-road lane, a quarter turn, then straight along the cross street."""
    sigma = int(rng.choice([-1, 1]))  # +1: travelling with the ego, -1: oncoming
    tau = int(rng.choice([-1, 1]))  # +1 left turn, -1 right turn
    radius = rng.uniform(8, 11) if tau > 0 else rng.uniform(4.5, 6)
    d_in = -sigma * lay.lane_width / 2
    exit_dir = sigma * tau  # +1: leaves along +d
    s_turn = lay.cross_s + exit_dir * lay.cross_half / 2 - sigma * radius
    approach = 60.0
    lane = lay.road.lane_path(d_in, s_turn - sigma * approach, sigma > 0)
    curv = lane.pieces[0][1]
    path = Path(lane.x0, lane.y0, lane.heading0, ((approach, curv), (np.pi / 2 * radius, tau / radius), (1e4, 0.0)))
    kind, verts = _vehicle(rng)
    while kind == "bus":
        kind, verts = _vehicle(rng)
    u0 = rng.uniform(approach - 30, approach + np.pi / 2 * radius + 15)
    return Agent("turning", Mover(path, rng.uniform(3, 7) * speed_scale, u0, t0), verts, 0.0, vehicle_circles(kind))


def _walker(lay: Layout, rng, t0: float, speed_scale: float) -> Agent:
    side = int(rng.choice([-1, 1]))
    offset = lay.half(side) + rng.uniform(2.0, max(2.1, lay.sidewalk - 0.4))
    path = lay.road.lane_path(side * offset, rng.uniform(-25, 40), bool(rng.uniform() < 0.5))
    verts = objects.pedestrian_mesh(rng, rng.uniform())
    return Agent(
        "walker", Mover(path, rng.uniform(0.9, 1.8) * speed_scale, 0.0, t0), verts, SIDEWALK_HEIGHT, np.array([[0.0, 0.0, 0.4]])
    )


def _zebra_walker(lay: Layout, rng, t0: float, speed_scale: float) -> Agent:
    edge = int(rng.choice([-1, 1]))
    s = lay.cross_s + edge * (lay.cross_half + 2.5) + rng.uniform(-1, 1)
    direction = int(rng.choice([-1, 1]))
    d = rng.uniform(-lay.half_right + 0.5, lay.half_left - 0.5)
    verts = objects.pedestrian_mesh(rng, rng.uniform())
    return Agent(
        "zebra",
        Mover(lay.road.radial_path(s, d, direction > 0), rng.uniform(1.0, 1.7) * speed_scale, 0.0, t0),
        verts,
        0.0,
        np.array([[0.0, 0.0, 0.4]]),
    )


_MAKERS = {
    "follow": lambda *a: _lane_vehicle(*a, oncoming=False),
    "oncoming": lambda *a: _lane_vehicle(*a, oncoming=True),
    "crossing": _crossing_vehicle,
    "turning": _turning_vehicle,
    "walker": _walker,
    "zebra": _zebra_walker,
}


def ego_circles() -> np.ndarray:
    """The ego car's footprint in the ego frame (origin at the rear axle, 4.8 m long)."""
    return np.array([[-0.1, 0.0, 1.15], [1.4, 0.0, 1.15], [2.9, 0.0, 1.15]])


def _overlap(a: np.ndarray, b: np.ndarray, margin: float = 0.3) -> bool:
    dist = np.linalg.norm(a[:, None, :2] - b[None, :, :2], axis=-1)
    return bool(np.any(dist < a[:, None, 2] + b[None, :, 2] + margin))


def spawn_agents(
    lay: Layout, rng: np.random.Generator, count: int, times: np.ndarray, ego: Mover, obstacles: Obstacles, speed_scale: float
) -> list[Agent]:
    """Up to ``count`` agents that stay clear of each other, the ego and obstacles at ``times``."""
    kinds = [k for k in KINDS if lay.cross_s is not None or k not in ("crossing", "turning", "zebra")]
    weights = np.array([WEIGHTS[KINDS.index(k)] for k in kinds])
    t0 = float(times[0])
    ego_at = [world_circles(ego_circles(), ego.road_pose(t)) for t in times]
    static = obstacles.array()
    agents: list[Agent] = []
    placed: list[list[np.ndarray]] = []
    for _ in range(40 * count + 40):
        if len(agents) >= count:
            break
        kind = kinds[rng.choice(len(kinds), p=weights / weights.sum())]
        agent = _MAKERS[kind](lay, rng, t0, speed_scale)
        circles = [world_circles(agent.circles, agent.road_pose(t)) for t in times]
        if not _clear(agent, lay, circles, ego_at, placed, static):
            continue
        agents.append(agent)
        placed.append(circles)
    return agents


def _clear(agent: Agent, lay: Layout, circles, ego_at, placed, static) -> bool:
    for i, c in enumerate(circles):
        if _overlap(c, ego_at[i], 0.6) or any(_overlap(c, other[i]) for other in placed):
            return False
        if agent.kind in ("walker", "zebra") and len(static) and _overlap(c, static, 0.1):
            return False
    sd = np.array([lay.road.to_sd(*c[:, :2].mean(0)) for c in circles])
    if np.hypot(*sd[0]) > 90:
        return False
    if agent.kind == "walker":
        return not any(lay.in_cross_gap(s - 0.5, s + 0.5) for s, _ in sd)
    if agent.kind == "zebra":
        return bool(np.all((sd[:, 1] > -lay.half_right + 0.3) & (sd[:, 1] < lay.half_left - 0.3)))
    return True
