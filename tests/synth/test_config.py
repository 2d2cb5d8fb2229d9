"""Config validation, presets and seed splits (no GL)."""

from __future__ import annotations

import pytest

from drivingscene.errors import InputError
from drivingscene.synth.config import PRESETS, SPLITS, SynthConfig, eval_fractions, resolve_config, split_seeds


def test_presets_resolve_and_flags_override_them():
    for name in PRESETS:
        cfg = resolve_config(name)
        for key, value in PRESETS[name].items():
            assert getattr(cfg, key) == value
    cfg = resolve_config("fast_ego", ego_speed=3.0, height=96, width=176)
    assert (cfg.ego_speed, cfg.height, cfg.width) == (3.0, 96, 176)
    assert resolve_config("noisy", num_moving=None).num_moving == SynthConfig().num_moving


@pytest.mark.parametrize(
    "overrides, flag",
    [
        ({"height": 0}, "--res"),
        ({"ego_speed": -1.0}, "--ego-speed"),
        ({"ego_speed": float("nan")}, "--ego-speed"),
        ({"num_moving": -2}, "--num-moving"),
        ({"keyframe_gap": 0.0}, "--keyframe-gap"),
        ({"noise_std": 2.0}, "--noise-std"),
        ({"blackout_camera": "CAM_TOP"}, "--blackout-camera"),
        ({"supersample": 0}, "--supersample"),
        ({"rig": "fisheye"}, "--rig"),
        ({"rig": "random", "blackout_camera": "CAM_5"}, "--blackout-camera"),
        ({"scene_style": "rural"}, "--scene-style"),
        ({"lighting": "night"}, "--lighting"),
        ({"photometric": -0.5}, "--photometric"),
        ({"ego_body": 1.01}, "--ego-body"),
        ({"capture_spread": float("inf")}, "--capture-spread"),
        ({"randomise_motion": 1}, "--randomise-motion"),
    ],
)
def test_bad_values_name_their_flag(overrides, flag):
    with pytest.raises(InputError, match=f"^{flag}: expected"):
        resolve_config("default", **overrides)


def test_unknown_preset():
    with pytest.raises(InputError, match="^--preset: expected one of default, easy"):
        resolve_config("hard")


def test_split_seed_ranges_are_disjoint():
    assert SPLITS == {"train": (0, 100_000), "val": (100_000, 110_000), "test": (200_000, 210_000)}
    assert list(split_seeds("val", 3)) == [100_000, 100_001, 100_002]
    assert list(split_seeds("test", 2, start=5)) == [200_005, 200_006]
    with pytest.raises(InputError, match="^--count"):
        split_seeds("val", 10_001)
    with pytest.raises(InputError, match="^--split"):
        split_seeds("dev", 1)


def test_eval_fractions_and_config_round_trip():
    assert eval_fractions(1) == [0.5]
    assert eval_fractions(3) == [0.25, 0.5, 0.75]
    cfg = resolve_config("blackout", height=64, width=112)
    assert SynthConfig.from_dict(cfg.to_dict()) == cfg
    with pytest.raises(InputError, match="unknown key"):
        SynthConfig.from_dict({**cfg.to_dict(), "fog": 1})


def test_old_config_dicts_get_the_fixed_benchmark_defaults():
    old = {k: v for k, v in SynthConfig().to_dict().items() if k not in ("rig", "photometric", "randomise_motion")}
    cfg = SynthConfig.from_dict(old)
    assert (cfg.rig, cfg.photometric, cfg.randomise_motion) == ("nuscenes", 0.0, False)
    assert resolve_config("blackout", blackout_camera="none").blackout_camera is None
    assert resolve_config("default", rig="random", blackout_camera="4").blackout_camera == "4"
