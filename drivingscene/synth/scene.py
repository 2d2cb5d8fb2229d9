"""One procedural scene: town, lighting, ego path and agents, built from (config, seed) only.

Three independent random streams are derived from the seed: ``[seed, 1]`` the town, lighting, ego
lane and world placement; ``[seed, 2]`` the moving agents; ``[seed, 3]`` image noise. A preset
that changes only speeds or image effects therefore keeps the same town.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from drivingscene.synth import streetscape, town
from drivingscene.synth.config import SynthConfig
from drivingscene.synth.meshes import MeshBuilder
from drivingscene.synth.motion import Mover, planar_pose
from drivingscene.synth.traffic import Agent, spawn_agents


@dataclass(frozen=True)
class Lighting:
    sun_dir: tuple[float, float, float]  # world frame, unit, towards the sun
    sun_color: tuple[float, float, float]  # linear RGB
    ambient: tuple[float, float, float]  # linear RGB from the sky hemisphere
    sky_zenith: tuple[float, float, float]  # display RGB
    sky_horizon: tuple[float, float, float]  # display RGB, also the haze colour
    haze_distance: float  # metres for 63 % haze
    cloud_cover: float  # 0..1
    cloud_offset: tuple[float, float]


@dataclass(frozen=True, eq=False)
class Scene:
    layout: town.Layout
    road_to_world: np.ndarray  # [4, 4] float64
    static_vertices: np.ndarray  # [N, VERTEX_FLOATS] road frame (the static "object")
    agents: tuple[Agent, ...]
    ego: Mover
    lighting: Lighting
    t0: float  # seconds, keyframe 0
    keyframe_gap: float  # seconds

    @property
    def keyframe_times(self) -> tuple[float, float]:
        return self.t0, self.t0 + self.keyframe_gap

    def ego_to_world(self, t: float) -> np.ndarray:
        """``[4, 4]`` float64 ego pose at time t (exact, from the path)."""
        return self.road_to_world @ self.ego.road_pose(t)

    def agents_to_world(self, t: float) -> np.ndarray:
        """``[A, 4, 4]`` float64 object-to-world poses of the agents at time t."""
        return np.array([self.road_to_world @ a.road_pose(t) for a in self.agents]).reshape(-1, 4, 4)


def sample_lighting(rng: np.random.Generator) -> Lighting:
    elevation, azimuth = np.radians(rng.uniform(22, 62)), rng.uniform(-np.pi, np.pi)
    sun = (np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation))
    warm = rng.uniform(0, 1)
    sun_color = np.array([1.0, 0.93 - 0.05 * warm, 0.82 - 0.12 * warm]) * rng.uniform(1.7, 2.2)
    ambient = np.array([0.55, 0.62, 0.78]) * rng.uniform(0.45, 0.65)
    zenith = np.array([0.25, 0.45, 0.78]) * rng.uniform(0.85, 1.1)
    horizon = np.array([0.72, 0.80, 0.88]) * rng.uniform(0.92, 1.05)
    return Lighting(
        tuple(float(v) for v in sun),
        tuple(sun_color.tolist()),
        tuple(ambient.tolist()),
        tuple(np.clip(zenith, 0, 1).tolist()),
        tuple(np.clip(horizon, 0, 1).tolist()),
        float(rng.uniform(250, 500)),
        float(rng.uniform(0.1, 0.8)),
        tuple(rng.uniform(-100, 100, 2).tolist()),
    )


def build_static(layout: town.Layout, rng: np.random.Generator) -> tuple[np.ndarray, streetscape.Obstacles]:
    """Every static mesh of the town in road coordinates, and the obstacles moving things avoid."""
    b = MeshBuilder()
    obstacles = streetscape.Obstacles()
    town.road_surfaces(b, layout, rng)
    town.road_markings(b, layout, rng)
    streetscape.parked_cars(b, layout, rng, obstacles)
    streetscape.trees_and_furniture(b, layout, rng, obstacles)
    streetscape.buildings(b, layout, rng)
    return b.build(), obstacles


def build_scene(config: SynthConfig, seed: int) -> Scene:
    """The scene of ``seed`` under ``config`` (deterministic)."""
    rng = np.random.default_rng([seed, 1])
    layout = town.sample_layout(rng)
    lighting = sample_lighting(rng)
    t0 = float(rng.uniform(2.0, 30.0))
    road_to_world = planar_pose(*rng.uniform(-400, 400, 2), rng.uniform(-np.pi, np.pi), rng.uniform(-5, 25))
    ego_lane = 0 if layout.lanes_per_dir == 1 or rng.uniform() < 0.6 else 1
    ego = Mover(layout.road.lane_path(-(ego_lane + 0.5) * layout.lane_width, 0.0), config.ego_speed, 0.0, t0)
    static, obstacles = build_static(layout, rng)
    times = t0 + config.keyframe_gap * np.linspace(-0.1, 1.1, 9)
    agents = spawn_agents(
        layout, np.random.default_rng([seed, 2]), config.num_moving, times, ego, obstacles, config.object_speed_scale
    )
    return Scene(layout, road_to_world, static, tuple(agents), ego, lighting, t0, config.keyframe_gap)
