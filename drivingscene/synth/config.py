"""Configuration of the synthetic benchmark: difficulty knobs, named presets and seed splits."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields, replace

from drivingscene.errors import InputError
from drivingscene.synth.rigs import RIG_KINDS, guaranteed_camera_names

SCENE_STYLES = ("town", "suburban", "mixed")
LIGHTINGS = ("default", "varied")


@dataclass(frozen=True)
class SynthConfig:
    """Every knob of one generated pair. Randomness comes only from the seed."""

    height: int = 176  # pixels
    width: int = 320  # pixels
    ego_speed: float = 8.0  # m/s along the lane
    object_speed_scale: float = 1.0  # multiplies every moving object's own speed
    num_moving: int = 8  # moving vehicles and pedestrians
    keyframe_gap: float = 0.5  # seconds between keyframe 0 and keyframe 1
    texture_strength: float = 1.0  # amplitude of procedural texture detail (0 = flat colours)
    exposure_change: float = 1.0  # brightness gain of keyframe 1 relative to keyframe 0
    noise_std: float = 0.0  # std of additive Gaussian image noise, in [0, 1] intensity units
    blackout_camera: str | None = None  # a camera name of the rig or an index: its images are black
    num_eval: int = 1  # evaluation frames evenly spaced strictly between the keyframes
    supersample: int = 3  # colour is rendered s x s times larger and box-filtered
    # Randomisation (the defaults reproduce the fixed benchmark byte for byte):
    rig: str = "nuscenes"  # nuscenes | ddad (fixed rigs) | random (5-8 cameras drawn per seed)
    scene_style: str = "town"  # town | suburban | mixed (either, per seed)
    lighting: str = "default"  # default | varied (clear, hazy, overcast, golden, bright white sky)
    photometric: float = 0.0  # strength in [0, 1] of per-camera exposure, colour, lens and JPEG jitter
    ego_body: float = 0.0  # probability per camera of the ego car's body at the image bottom (masked)
    capture_spread: float = 0.0  # seconds spanned by one frame's camera triggers (0 = simultaneous)
    randomise_motion: bool = False  # per seed ego speed, keyframe gap and object speed scale

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, values: dict) -> SynthConfig:
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise InputError(f"synth config: unknown key(s) {', '.join(unknown)}; expected some of {', '.join(sorted(known))}")
        return validate_config(cls(**values))


PRESETS: dict[str, dict] = {
    "default": {},
    "easy": {"ego_speed": 5.0, "object_speed_scale": 0.5, "num_moving": 4, "texture_strength": 1.25},
    "fast_ego": {"ego_speed": 16.0},
    "fast_objects": {"object_speed_scale": 2.0},
    "crowded": {"num_moving": 20},
    "long_gap": {"keyframe_gap": 1.0},
    "low_texture": {"texture_strength": 0.25},
    "exposure": {"exposure_change": 1.3},
    "noisy": {"noise_std": 0.03},
    "blackout": {"blackout_camera": "CAM_FRONT_LEFT"},
    "randomised": {
        "rig": "random",
        "scene_style": "mixed",
        "lighting": "varied",
        "photometric": 1.0,
        "ego_body": 0.6,
        "capture_spread": 0.04,
        "randomise_motion": True,
    },
}
PRESET_HELP: dict[str, str] = {
    "default": "8 m/s ego, 8 moving objects, 0.5 s gap, full texture",
    "easy": "slow ego and objects, few movers, strong texture",
    "fast_ego": "ego at 16 m/s (8 m between keyframes)",
    "fast_objects": "moving objects twice as fast",
    "crowded": "20 moving objects",
    "long_gap": "1.0 s between keyframes",
    "low_texture": "texture detail at 25 %",
    "exposure": "keyframe 1 is 30 % brighter than keyframe 0",
    "noisy": "Gaussian noise, std 0.03 (about 8 grey levels)",
    "blackout": "CAM_FRONT_LEFT is black in every frame",
    "randomised": "random 5-8 camera rigs, towns and leafy suburbs, varied skies, camera jitter, ego body, staggered triggers, random motion",
}

# Seeds of each split: [start, stop). A dataset of N pairs uses the first N seeds (after --start).
SPLITS: dict[str, tuple[int, int]] = {
    "train": (0, 100_000),
    "val": (100_000, 110_000),
    "test": (200_000, 210_000),
}


def _check(ok: bool, flag: str, expected: str, found) -> None:
    if not ok:
        raise InputError(f"{flag}: expected {expected}, found {found!r}")


def validate_config(cfg: SynthConfig) -> SynthConfig:
    """Return ``cfg`` if every knob is usable, else raise ``InputError`` naming the flag."""
    _check(cfg.height >= 8 and cfg.width >= 8, "--res", "HxW with both sides >= 8 pixels", f"{cfg.height}x{cfg.width}")
    _check(cfg.height * cfg.width <= 1080 * 1920, "--res", "at most 1080x1920", f"{cfg.height}x{cfg.width}")
    finite = {
        k: getattr(cfg, k)
        for k in ("ego_speed", "object_speed_scale", "keyframe_gap", "texture_strength", "exposure_change", "noise_std")
    }
    for key, value in finite.items():
        _check(isinstance(value, (int, float)) and math.isfinite(value), f"--{key.replace('_', '-')}", "a finite number", value)
    _check(0 <= cfg.ego_speed <= 40, "--ego-speed", "a speed in [0, 40] m/s", cfg.ego_speed)
    _check(0 <= cfg.object_speed_scale <= 5, "--object-speed-scale", "a factor in [0, 5]", cfg.object_speed_scale)
    _check(0 <= cfg.num_moving <= 60, "--num-moving", "an integer in [0, 60]", cfg.num_moving)
    _check(0.05 <= cfg.keyframe_gap <= 3, "--keyframe-gap", "seconds in [0.05, 3]", cfg.keyframe_gap)
    _check(0 <= cfg.texture_strength <= 3, "--texture-strength", "a value in [0, 3]", cfg.texture_strength)
    _check(0.1 <= cfg.exposure_change <= 10, "--exposure-change", "a gain in [0.1, 10]", cfg.exposure_change)
    _check(0 <= cfg.noise_std <= 1, "--noise-std", "a standard deviation in [0, 1]", cfg.noise_std)
    _check(0 <= cfg.num_eval <= 16, "--num-eval", "an integer in [0, 16]", cfg.num_eval)
    _check(1 <= cfg.supersample <= 6, "--supersample", "an integer in [1, 6]", cfg.supersample)
    _validate_randomisation(cfg)
    return cfg


def _validate_randomisation(cfg: SynthConfig) -> None:
    _check(cfg.rig in RIG_KINDS, "--rig", f"one of {', '.join(RIG_KINDS)}", cfg.rig)
    names = guaranteed_camera_names(cfg.rig)
    _check(
        cfg.blackout_camera is None or cfg.blackout_camera in names or cfg.blackout_camera in [str(i) for i in range(len(names))],
        "--blackout-camera",
        f"one of {', '.join(names)}, an index 0-{len(names) - 1} or none (rig {cfg.rig})",
        cfg.blackout_camera,
    )
    _check(cfg.scene_style in SCENE_STYLES, "--scene-style", f"one of {', '.join(SCENE_STYLES)}", cfg.scene_style)
    _check(cfg.lighting in LIGHTINGS, "--lighting", f"one of {', '.join(LIGHTINGS)}", cfg.lighting)
    for flag, value, hi, what in (
        ("--photometric", cfg.photometric, 1.0, "a strength in [0, 1]"),
        ("--ego-body", cfg.ego_body, 1.0, "a probability in [0, 1]"),
        ("--capture-spread", cfg.capture_spread, 0.1, "seconds in [0, 0.1]"),
    ):
        ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value) and 0 <= value <= hi
        _check(ok, flag, what, value)
    _check(isinstance(cfg.randomise_motion, bool), "--randomise-motion", "true or false", cfg.randomise_motion)


def resolve_config(preset: str = "default", **overrides) -> SynthConfig:
    """The preset's config with ``overrides`` (knobs left ``None`` keep the preset's value;
    ``blackout_camera="none"`` clears the preset's camera)."""
    if preset not in PRESETS:
        raise InputError(f"--preset: expected one of {', '.join(PRESETS)}, found {preset!r}")
    values = {**PRESETS[preset], **{k: v for k, v in overrides.items() if v is not None}}
    if values.get("blackout_camera") == "none":
        values["blackout_camera"] = None
    return validate_config(replace(SynthConfig(), **values))


def split_seeds(split: str, count: int, start: int = 0) -> range:
    """The seeds of the first ``count`` pairs of ``split`` after skipping ``start``."""
    if split not in SPLITS:
        raise InputError(f"--split: expected one of {', '.join(SPLITS)}, found {split!r}")
    lo, hi = SPLITS[split]
    _check(count >= 1, "--count", "a positive number of pairs", count)
    _check(start >= 0, "--start", "a non-negative offset", start)
    _check(lo + start + count <= hi, "--count", f"start + count <= {hi - lo} seeds in split {split}", start + count)
    return range(lo + start, lo + start + count)


def eval_fractions(num_eval: int) -> list[float]:
    """Normalised times of the evaluation frames: evenly spaced strictly inside (0, 1)."""
    return [(i + 1) / (num_eval + 1) for i in range(num_eval)]
