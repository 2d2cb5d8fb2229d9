"""One procedural scene: town or suburb, lighting, ego path and agents, built from (config, seed) only.

Independent random streams are derived from the seed: ``[seed, 1]`` the town, lighting, ego lane and
world placement; ``[seed, 2]`` the moving agents; ``[seed, 3]`` image noise. A preset that changes
only speeds or image effects therefore keeps the same town. The randomisation knobs draw only from
new streams (``[seed, 4]`` and up; see ``streams.STREAMS``), so with them off every pair is byte-identical
to the fixed benchmark, and a suburb keeps its seed's lighting, world placement and t0.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from drivingscene.synth import streetscape, suburb, town
from drivingscene.synth.config import SynthConfig
from drivingscene.synth.lighting import Lighting, sample_lighting, sample_varied_lighting
from drivingscene.synth.meshes import MeshBuilder
from drivingscene.synth.motion import Mover, planar_pose
from drivingscene.synth.streams import stream
from drivingscene.synth.traffic import Agent, spawn_agents

__all__ = ["Lighting", "Motion", "Scene", "build_scene", "sample_lighting", "scene_motion", "scene_style"]


@dataclass(frozen=True)
class Motion:
    ego_speed: float  # m/s
    keyframe_gap: float  # seconds
    object_speed_scale: float


def scene_motion(config: SynthConfig, seed: int) -> Motion:
    """The config's speeds and gap, or under ``randomise_motion`` a draw per seed: ego 0-16 m/s
    (8 % stopped at exactly 0), a keyframe gap of 0.1-0.6 s (10 Hz DDAD-like to 2 Hz nuScenes-like),
    objects at 0.3-1.5 times their own speed."""
    if not config.randomise_motion:
        return Motion(config.ego_speed, config.keyframe_gap, config.object_speed_scale)
    rng = stream(seed, "motion")
    speed = 0.0 if rng.uniform() < 0.08 else float(rng.uniform(0.5, 16.0))
    pick = rng.uniform()
    gap = 0.1 if pick < 0.3 else 0.5 if pick < 0.55 else float(rng.uniform(0.1, 0.6))
    return Motion(speed, gap, float(rng.uniform(0.3, 1.5)))


def scene_style(config: SynthConfig, seed: int) -> str:
    """ "town" or "suburban" for this seed."""
    if config.scene_style != "mixed":
        return config.scene_style
    return "suburban" if stream(seed, "style").uniform() < 0.5 else "town"


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
    style: str = "town"  # "town" or "suburban"

    @property
    def keyframe_times(self) -> tuple[float, float]:
        return self.t0, self.t0 + self.keyframe_gap

    def ego_to_world(self, t: float) -> np.ndarray:
        """``[4, 4]`` float64 ego pose at time t (exact, from the path)."""
        return self.road_to_world @ self.ego.road_pose(t)

    def agents_to_world(self, t: float) -> np.ndarray:
        """``[A, 4, 4]`` float64 object-to-world poses of the agents at time t."""
        return np.array([self.road_to_world @ a.road_pose(t) for a in self.agents]).reshape(-1, 4, 4)


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
    style = scene_style(config, seed)
    motion = scene_motion(config, seed)
    layout = town.sample_layout(rng)  # drawn for a suburb too: the stream's later draws stay the seed's
    lighting = sample_lighting(rng)
    if config.lighting == "varied":
        lighting = sample_varied_lighting(stream(seed, "lighting"))
    t0 = float(rng.uniform(2.0, 30.0))
    road_to_world = planar_pose(*rng.uniform(-400, 400, 2), rng.uniform(-np.pi, np.pi), rng.uniform(-5, 25))
    streets = rng  # the town stream builds a town; a suburb has its own
    if style == "suburban":
        streets = stream(seed, "suburb")
        layout = suburb.sample_layout(streets)
    ego_lane = 0 if layout.lanes_per_dir == 1 or streets.uniform() < 0.6 else 1
    ego = Mover(layout.road.lane_path(-(ego_lane + 0.5) * layout.lane_width, 0.0), motion.ego_speed, 0.0, t0)
    if style == "suburban":
        static, obstacles = suburb.build_static(layout, streets)
    else:
        static, obstacles = build_static(layout, rng)
    times = t0 + motion.keyframe_gap * np.linspace(-0.1, 1.1, 9)
    if config.capture_spread > 0:  # agents also stay clear at the earliest and latest camera trigger
        times = np.concatenate([times, t0 + np.array([-config.capture_spread, motion.keyframe_gap + config.capture_spread])])
    agents = spawn_agents(
        layout, np.random.default_rng([seed, 2]), config.num_moving, times, ego, obstacles, motion.object_speed_scale
    )
    return Scene(layout, road_to_world, static, tuple(agents), ego, lighting, t0, motion.keyframe_gap, style)
