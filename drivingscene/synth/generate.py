"""Composition root: (config, seed) -> a ``FramePair`` with every ground-truth key.

Image path: rendered float colours -> ego body (``ego_body``) -> per-camera look (``photometric``)
-> exposure change and noise -> uint8 -> JPEG (``photometric``) -> blackout. Under
``capture_spread`` every image is rendered at its camera's own trigger time (ego pose and moving
objects), and the ground truth of camera v relates its two keyframe images at their own times.
"""

from __future__ import annotations

import time

import numpy as np

from drivingscene.data import FramePair
from drivingscene.synth import ego_body, photometric
from drivingscene.synth.config import SynthConfig, eval_fractions, validate_config
from drivingscene.synth.ground_truth import keyframe_truth
from drivingscene.synth.render import SynthRenderer, View
from drivingscene.synth.rig import CAMERA_NAMES, Rig
from drivingscene.synth.rigs import camera_index, camera_yaws, make_rig_of_kind
from drivingscene.synth.scene import Scene, build_scene
from drivingscene.synth.streams import stream


def scene_view(scene: Scene, rig: Rig, t: float | np.ndarray) -> View:
    """Camera and object poses at time t (seconds), or at each camera's own time ``t`` [V]."""
    if np.ndim(t) == 0:
        return View(scene.ego_to_world(t)[None] @ rig.cam_to_ego, scene.road_to_world, scene.agents_to_world(t))
    egos = np.stack([scene.ego_to_world(float(s)) for s in t])
    return View(egos @ rig.cam_to_ego, scene.road_to_world, np.stack([scene.agents_to_world(float(s)) for s in t]))


def shading_uniforms(scene: Scene, config: SynthConfig) -> dict:
    light = scene.lighting
    return {
        "u_sun_dir": light.sun_dir,
        "u_sun_color": light.sun_color,
        "u_ambient": light.ambient,
        "u_haze_color": light.sky_horizon,
        "u_haze_distance": light.haze_distance,
        "u_texture": float(config.texture_strength),
        "u_ground_z": float(scene.road_to_world[2, 3]),
        "u_zenith": light.sky_zenith,
        "u_horizon": light.sky_horizon,
        "u_cloud_cover": light.cloud_cover,
        "u_cloud_offset": light.cloud_offset,
        "u_cloud_color": light.cloud_color,
        "u_glow_color": light.glow_color,
        "u_band_scale": float(config.supersample),
    }


def file_rig(config: SynthConfig, seed: int = 0) -> Rig:
    """The rig as stored in the file (float32), used for rendering too so the file is exact."""
    rig = make_rig_of_kind(config.rig, config.height, config.width, seed)
    return Rig(
        rig.camera_names,
        rig.intrinsics.astype(np.float32).astype(np.float64),
        rig.cam_to_ego.astype(np.float32).astype(np.float64),
        rig.height,
        rig.width,
    )


def capture_offsets(rig: Rig, spread: float, seed: int) -> np.ndarray:
    """``[V]`` seconds from a frame's time to each camera's trigger: a spinning LiDAR triggers each
    camera as it sweeps past (clockwise from a random start), so the offsets span ``spread``
    around the frame time in the cameras' order around the car (nuScenes: about 40 ms)."""
    start = stream(seed, "capture").uniform(-180.0, 180.0)
    swept = (start - camera_yaws(rig.cam_to_ego)) % 360.0  # degrees swept clockwise until each camera
    return spread * (swept / 360.0 - 0.5)


def finish_images(
    colours: np.ndarray,
    fractions: list[float],
    config: SynthConfig,
    seed: int,
    camera_names: tuple[str, ...] = CAMERA_NAMES,
    jpeg_qualities: np.ndarray | None = None,
) -> np.ndarray:
    """Exposure gain, noise, JPEG and blackout on float images ``[T, V, H, W, 3]`` at normalised
    times ``fractions``; returns uint8. Keyframe 1 gets gain ``exposure_change``, others interpolate."""
    rng = np.random.default_rng([seed, 3])
    out = np.empty(colours.shape, np.uint8)
    for i, (image, frac) in enumerate(zip(colours, fractions)):
        gain = 1.0 + (config.exposure_change - 1.0) * frac
        value = image.astype(np.float64) * gain
        if config.noise_std > 0:
            value = value + rng.normal(0.0, config.noise_std, value.shape)
        out[i] = np.round(np.clip(value, 0.0, 1.0) * 255.0).astype(np.uint8)
    if jpeg_qualities is not None:
        out = photometric.jpeg_round_trip(out, jpeg_qualities)
    if config.blackout_camera is not None:
        out[:, camera_index(camera_names, config.blackout_camera)] = 0
    return out


def camera_images(colours: np.ndarray, fractions: list[float], config: SynthConfig, seed: int, rig: Rig):
    """uint8 images ``[T, V, H, W, 3]`` from rendered colours, and the valid mask ``[V, H, W]``
    (None without an ego body)."""
    body = None
    if config.ego_body > 0:
        yaws = camera_yaws(rig.cam_to_ego)
        body = ego_body.sample_ego_body(stream(seed, "ego_body"), config.ego_body, yaws, rig.height, rig.width)
    if body is not None:
        colours = ego_body.composite(colours, body)
    qualities = None
    if config.photometric > 0:
        rng = stream(seed, "photometric")
        looks = photometric.sample_looks(rng, config.photometric, len(colours), len(rig.camera_names))
        colours = photometric.apply_looks(colours, looks, rng)
        qualities = looks.jpeg_qualities if looks.jpeg_qualities.any() else None
    images = finish_images(colours, fractions, config, seed, rig.camera_names, qualities)
    return images, None if body is None else body.valid_mask()


class _Stopwatch:
    """Records seconds between laps into ``out`` (does nothing when ``out`` is None)."""

    def __init__(self, out: dict[str, float] | None) -> None:
        self.out = out
        self.last = time.perf_counter()

    def lap(self, name: str) -> None:
        now = time.perf_counter()
        if self.out is not None:
            self.out[name] = self.out.get(name, 0.0) + now - self.last
        self.last = now


def _dynamic_mask(buffers: tuple[np.ndarray, np.ndarray, np.ndarray]) -> np.ndarray:
    """``[V, H, W]`` bool: pixels showing a moving object, from a geometry pass."""
    now, other, _ = buffers
    return (other[..., 3] > 0.5) & (now[..., 3] > 0.5)


def _render(renderer: SynthRenderer, scene: Scene, rig: Rig, views: list[View], config: SynthConfig, clock) -> tuple:
    """Colours ``[T, V, H, W, 3]``, the two keyframes' truths and the eval frames' dynamic masks."""
    size = (config.height, config.width)
    gpu = renderer.upload(scene.static_vertices, [a.vertices for a in scene.agents])
    try:
        shading = shading_uniforms(scene, config)
        colours = np.stack([renderer.render_color(gpu, v, rig.intrinsics, size, config.supersample, shading) for v in views])
        clock.lap("colour")
        buffers = [renderer.render_geometry(gpu, views[k], views[1 - k], rig.intrinsics, size) for k in (0, 1)]
        eval_dynamic = [_dynamic_mask(renderer.render_geometry(gpu, v, v, rig.intrinsics, size)) for v in views[2:]]
    finally:
        gpu.release()
    truths = [keyframe_truth(*buffers[k], rig.intrinsics, views[k].cams_to_world, views[1 - k].cams_to_world) for k in (0, 1)]
    return colours, truths, eval_dynamic


def _capture_keys(scene: Scene, camera_times: list[np.ndarray]) -> dict:
    """The per-image capture keys of a pair with staggered triggers (``camera_times``: [V] per frame)."""
    poses = [np.stack([scene.ego_to_world(float(t)) for t in times]) for times in camera_times]
    keys = {"camera_timestamps": np.stack(camera_times[:2]), "camera_ego_to_world": np.stack(poses[:2])}
    if len(camera_times) > 2:
        keys.update(eval_camera_timestamps=np.stack(camera_times[2:]), eval_camera_ego_to_world=np.stack(poses[2:]))
    return keys


def generate_pair(
    config: SynthConfig, seed: int, renderer: SynthRenderer | None = None, timings: dict[str, float] | None = None
) -> FramePair:
    """One frame pair of the benchmark with exact ground truth (deterministic in config and seed).

    Pass a ``SynthRenderer`` to reuse its GL context and programs across pairs; pass a dict as
    ``timings`` to receive the seconds spent in each stage (for the benchmark).
    """
    clock = _Stopwatch(timings)
    validate_config(config)
    scene = build_scene(config, seed)
    clock.lap("scene")
    rig = file_rig(config, seed)
    renderer = renderer if renderer is not None else SynthRenderer()
    t0, t1 = scene.keyframe_times
    fractions = [0.0, 1.0, *eval_fractions(config.num_eval)]
    times = [t0 + f * scene.keyframe_gap for f in fractions]
    camera_times = None
    if config.capture_spread > 0:
        offsets = capture_offsets(rig, config.capture_spread, seed)
        camera_times = [t + offsets for t in times]
    views = [scene_view(scene, rig, t) for t in (camera_times or times)]
    colours, truths, eval_dynamic = _render(renderer, scene, rig, views, config, clock)
    clock.lap("ground_truth")
    images, valid_mask = camera_images(colours, fractions, config, seed, rig)
    clock.lap("images")
    has_eval = config.num_eval > 0
    return FramePair(
        images=images[:2],
        intrinsics=rig.intrinsics.astype(np.float32),
        cam_to_ego=rig.cam_to_ego.astype(np.float32),
        ego_to_world=np.stack([scene.ego_to_world(t0), scene.ego_to_world(t1)]),
        timestamps=np.array([t0, t1], np.float64),
        camera_names=rig.camera_names,
        gt_depth=np.stack([t.depth for t in truths]),
        gt_flow=np.stack([t.flow for t in truths]),
        gt_scene_flow=np.stack([t.scene_flow for t in truths]),
        gt_dynamic=np.stack([t.dynamic for t in truths]),
        eval_images=images[2:] if has_eval else None,
        eval_timestamps=np.array(times[2:], np.float64) if has_eval else None,
        eval_ego_to_world=np.stack([scene.ego_to_world(t) for t in times[2:]]) if has_eval else None,
        eval_dynamic=np.stack(eval_dynamic) if has_eval else None,
        valid_mask=valid_mask,
        **(_capture_keys(scene, camera_times) if camera_times is not None else {}),
    )
