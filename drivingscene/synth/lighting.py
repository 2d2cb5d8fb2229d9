"""Sun, sky and haze of a scene: the default fair-weather draw, and varied weather for the
randomised benchmark (clear blue, hazy, overcast, low golden sun, a bright midday with a near-white
sky, broken cloud). Lighting is the same at every time of a pair."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


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
    cloud_color: tuple[float, float, float] = (0.93, 0.94, 0.96)  # display RGB of lit cloud
    glow_color: tuple[float, float, float] = (1.0, 0.9, 0.7)  # display RGB of the sun's disc and halo


def _tuple(values) -> tuple[float, ...]:
    return tuple(float(v) for v in values)


def sun_direction(elevation_deg: float, azimuth: float) -> tuple[float, float, float]:
    elevation = np.radians(elevation_deg)
    return (np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation))


def sample_lighting(rng: np.random.Generator) -> Lighting:
    """The fixed benchmark's fair weather (draws from the town stream, so its order is frozen)."""
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


# weather: (probability, sun elevation range in degrees, sun strength, ambient strength, zenith
# colour, horizon colour, haze distance range in metres, cloud cover range, cloud colour)
WEATHER: dict[str, tuple] = {
    "clear": (0.22, (25, 65), 2.1, 0.5, (0.18, 0.40, 0.80), (0.70, 0.80, 0.90), (350, 700), (0.0, 0.3), (0.95, 0.95, 0.97)),
    "bright": (0.2, (45, 75), 2.6, 0.65, (0.78, 0.86, 0.97), (1.0, 1.0, 1.0), (300, 600), (0.0, 0.5), (1.0, 1.0, 1.0)),
    "hazy": (0.14, (20, 55), 1.5, 0.7, (0.55, 0.65, 0.78), (0.85, 0.86, 0.86), (110, 240), (0.0, 0.4), (0.92, 0.92, 0.92)),
    "overcast": (0.18, (30, 70), 0.35, 1.25, (0.70, 0.72, 0.75), (0.82, 0.83, 0.84), (180, 400), (0.95, 1.0), (0.78, 0.79, 0.81)),
    "golden": (0.11, (4, 14), 1.9, 0.42, (0.30, 0.45, 0.72), (0.95, 0.78, 0.58), (200, 450), (0.0, 0.5), (1.0, 0.86, 0.72)),
    "broken": (0.15, (25, 60), 1.9, 0.6, (0.22, 0.42, 0.78), (0.75, 0.80, 0.86), (250, 500), (0.55, 0.9), (0.92, 0.93, 0.95)),
}


def sample_varied_lighting(rng: np.random.Generator) -> Lighting:
    """One weather of ``WEATHER`` with jittered sun, sky and cloud."""
    names = list(WEATHER)
    weights = np.array([WEATHER[n][0] for n in names])
    name = names[rng.choice(len(names), p=weights / weights.sum())]
    _, elevation, sun_gain, ambient_gain, zenith, horizon, haze, cover, cloud = WEATHER[name]
    sun = sun_direction(rng.uniform(*elevation), rng.uniform(-np.pi, np.pi))
    if name == "golden":
        sun_color = np.array([1.0, rng.uniform(0.62, 0.75), rng.uniform(0.35, 0.48)]) * sun_gain * rng.uniform(0.9, 1.1)
        glow = (1.0, 0.75, 0.45)
    else:
        warm = rng.uniform(0, 1)
        sun_color = np.array([1.0, 0.95 - 0.05 * warm, 0.88 - 0.1 * warm]) * sun_gain * rng.uniform(0.85, 1.15)
        glow = (1.0, 0.92, 0.78) if name != "overcast" else (0.0, 0.0, 0.0)  # no sun disc behind full cloud
    ambient = np.array([0.6, 0.65, 0.75]) * ambient_gain * rng.uniform(0.85, 1.15)
    if name == "overcast":
        ambient = np.full(3, 0.72) * ambient_gain * rng.uniform(0.85, 1.15)
    tint = rng.uniform(0.94, 1.06, 3)
    return Lighting(
        _tuple(sun),
        _tuple(sun_color),
        _tuple(ambient),
        _tuple(np.clip(np.array(zenith) * tint * rng.uniform(0.9, 1.08), 0, 1)),
        _tuple(np.clip(np.array(horizon) * rng.uniform(0.95, 1.04), 0, 1)),
        float(rng.uniform(*haze)),
        float(rng.uniform(*cover)),
        _tuple(rng.uniform(-100, 100, 2)),
        _tuple(np.clip(np.array(cloud) * rng.uniform(0.92, 1.03), 0, 1)),
        glow,
    )
