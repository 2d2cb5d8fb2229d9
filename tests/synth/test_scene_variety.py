"""Scene style, varied lighting and randomised motion (scene building only, no GL)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from drivingscene.synth.config import SynthConfig
from drivingscene.synth.lighting import WEATHER, sample_varied_lighting
from drivingscene.synth.meshes import MATERIALS
from drivingscene.synth.scene import Motion, build_scene, scene_motion, scene_style
from drivingscene.synth.streams import stream

BASE = SynthConfig(height=48, width=88)


def _materials(scene) -> set[str]:
    names = {i: n for n, i in MATERIALS.items()}
    return {names[int(m)] for m in np.unique(scene.static_vertices[:, 11])}


def test_motion_is_the_configs_unless_randomised():
    assert scene_motion(BASE, 3) == Motion(8.0, 0.5, 1.0)
    draws = [scene_motion(replace(BASE, randomise_motion=True), seed) for seed in range(400)]
    speeds = np.array([d.ego_speed for d in draws])
    gaps = np.array([d.keyframe_gap for d in draws])
    scales = np.array([d.object_speed_scale for d in draws])
    assert 0.04 < np.mean(speeds == 0) < 0.13 and speeds.max() <= 16 and speeds.max() > 14
    assert np.all((gaps >= 0.1) & (gaps <= 0.6)) and np.mean(gaps == 0.1) > 0.2 and np.mean(gaps == 0.5) > 0.15
    assert np.all((scales >= 0.3) & (scales <= 1.5))
    assert scene_motion(replace(BASE, randomise_motion=True), 11) == draws[11]


def test_randomised_motion_reaches_the_scene():
    config = replace(BASE, randomise_motion=True)
    seed = next(
        s for s in range(50) if scene_motion(config, s).keyframe_gap not in (0.5,) and scene_motion(config, s).ego_speed > 1
    )
    scene, motion = build_scene(config, seed), scene_motion(config, seed)
    assert scene.keyframe_gap == motion.keyframe_gap and scene.ego.speed == motion.ego_speed


def test_mixed_style_draws_both_and_suburbs_look_suburban():
    styles = [scene_style(replace(BASE, scene_style="mixed"), seed) for seed in range(40)]
    assert 10 < styles.count("suburban") < 30 and set(styles) == {"town", "suburban"}
    town = build_scene(BASE, 5)
    suburb = build_scene(replace(BASE, scene_style="suburban"), 5)
    assert suburb.style == "suburban" and town.style == "town"
    assert {"grass", "siding", "shingle", "foliage", "bark", "asphalt"} <= _materials(suburb)
    assert not {"grass", "siding", "shingle", "slab"} & _materials(town)
    assert len(suburb.static_vertices) < 3 * 110_000  # a render budget: about a second per pair at 96x176
    foliage = suburb.static_vertices[:, 11] == MATERIALS["foliage"]
    assert foliage.mean() > 0.5  # many trees
    # the seed's lighting, t0 and world placement are the town's: only the streets changed
    assert suburb.lighting == town.lighting and suburb.t0 == town.t0
    np.testing.assert_array_equal(suburb.road_to_world, town.road_to_world)


def test_varied_lighting_covers_the_weathers():
    lights = [sample_varied_lighting(stream(seed, "lighting")) for seed in range(300)]
    elevations = np.degrees(np.arcsin([light.sun_dir[2] for light in lights]))
    assert elevations.min() < 14 and elevations.max() > 60  # golden hour to midday
    assert any(light.glow_color == (0.0, 0.0, 0.0) and light.cloud_cover > 0.9 for light in lights)  # overcast
    assert any(min(light.sky_horizon) > 0.93 for light in lights)  # a near-white sky
    assert min(light.haze_distance for light in lights) < 200 and len(WEATHER) == 6
    for light in lights:
        assert all(0 <= c <= 1 for c in (*light.sky_zenith, *light.sky_horizon, *light.cloud_color))


@pytest.mark.parametrize("style", ["town", "suburban"])
def test_scenes_are_deterministic(style):
    config = replace(BASE, scene_style=style, lighting="varied")
    a, b = build_scene(config, 9), build_scene(config, 9)
    np.testing.assert_array_equal(a.static_vertices, b.static_vertices)
    assert a.lighting == b.lighting and len(a.agents) == len(b.agents)
