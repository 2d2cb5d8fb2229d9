"""Each difficulty knob does what it says, on the same scene (same seed) at low resolution."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from drivingscene.geometry import rigid_flow
from drivingscene.geometry.flow import cams_to_world
from drivingscene.synth.config import PRESETS, resolve_config
from drivingscene.synth.scene import build_scene
from tests.synth.conftest import SMALL, TEST_SEED

pytestmark = pytest.mark.gl


def _with(**overrides):
    return replace(SMALL, **overrides)


def test_blackout_camera_is_black_and_keeps_ground_truth(generate, small_pair):
    pair = generate(_with(blackout_camera="CAM_BACK"))
    v = pair.camera_names.index("CAM_BACK")
    assert not pair.images[:, v].any() and not pair.eval_images[:, v].any()
    others = [i for i in range(6) if i != v]
    np.testing.assert_array_equal(pair.images[:, others], small_pair.images[:, others])
    np.testing.assert_array_equal(pair.gt_depth, small_pair.gt_depth)
    assert (pair.gt_depth[:, v] > 0).any()


def test_exposure_change_scales_keyframe_1_and_interpolates(generate, small_pair):
    pair = generate(_with(exposure_change=1.3))
    np.testing.assert_array_equal(pair.images[0], small_pair.images[0])
    for frame, ref, gain in ((pair.images[1], small_pair.images[1], 1.3), (pair.eval_images[0], small_pair.eval_images[0], 1.15)):
        unclipped = ref < 180
        ratio = frame[unclipped].astype(np.float64).sum() / ref[unclipped].astype(np.float64).sum()
        assert ratio == pytest.approx(gain, abs=0.01)
        assert np.abs(frame[unclipped] - np.round(ref[unclipped] * gain)).max() <= 2


def test_noise_has_the_requested_standard_deviation(generate, small_pair):
    pair = generate(_with(noise_std=0.03))
    diff = pair.images.astype(np.float64) - small_pair.images
    unclipped = (small_pair.images > 30) & (small_pair.images < 225)
    assert diff[unclipped].std() == pytest.approx(0.03 * 255, rel=0.08)
    assert abs(diff[unclipped].mean()) < 0.3


def _dynamic_residual(pair) -> float:
    """Median |gt flow - rigid flow| on moving-object pixels: the objects' own image motion."""
    poses = cams_to_world(torch.tensor(pair.cam_to_ego, dtype=torch.float64), torch.tensor(pair.ego_to_world))
    flow, _ = rigid_flow(
        torch.tensor(pair.gt_depth[0], dtype=torch.float64),
        torch.tensor(pair.intrinsics, dtype=torch.float64),
        poses[0],
        poses[1],
    )
    residual = np.linalg.norm(pair.gt_flow[0] - flow.numpy(), axis=-1)
    return float(np.median(residual[pair.gt_dynamic[0]]))


def test_faster_objects_move_further(generate, small_pair):
    fast = generate(_with(object_speed_scale=2.0))
    assert _dynamic_residual(fast) > 1.5 * _dynamic_residual(small_pair)
    slow = build_scene(SMALL, TEST_SEED)
    quick = build_scene(_with(object_speed_scale=2.0), TEST_SEED)
    assert [a.mover.speed * 2 for a in slow.agents][:3] == pytest.approx([a.mover.speed for a in quick.agents][:3])


def _surface_gradient(pair) -> float:
    """Mean image gradient inside surfaces (depth varies < 2 % between neighbours): texture, not edges."""
    grey = pair.images[0].astype(np.float64).mean(-1)
    depth = pair.gt_depth[0]
    gx, dx = np.abs(np.diff(grey, axis=-1)), np.abs(np.diff(depth, axis=-1))
    smooth = (dx < 0.02 * depth[..., 1:]) & (depth[..., 1:] > 0)
    return float(gx[smooth].mean())


def test_low_texture_has_weaker_surface_gradients(generate, small_pair):
    flat = generate(_with(texture_strength=0.25))
    none = generate(_with(texture_strength=0.0))
    full, low, zero = _surface_gradient(small_pair), _surface_gradient(flat), _surface_gradient(none)
    assert zero < low < full
    assert (low - zero) < 0.5 * (full - zero)


def test_ego_speed_gap_and_crowd_presets_change_the_scene_they_should():
    fast_ego = build_scene(resolve_config("fast_ego", height=64, width=112), TEST_SEED)
    t0 = fast_ego.t0
    assert np.linalg.norm(fast_ego.ego_to_world(t0 + 0.5)[:3, 3] - fast_ego.ego_to_world(t0)[:3, 3]) == pytest.approx(
        8.0, abs=0.01
    )
    assert build_scene(resolve_config("long_gap"), TEST_SEED).keyframe_times[1] - t0 == pytest.approx(1.0)
    assert len(build_scene(resolve_config("crowded"), TEST_SEED).agents) == 20
    assert len(build_scene(resolve_config("easy"), TEST_SEED).agents) == 4
    assert set(PRESETS) >= {
        "default",
        "easy",
        "fast_ego",
        "fast_objects",
        "crowded",
        "long_gap",
        "low_texture",
        "exposure",
        "noisy",
        "blackout",
    }


def test_same_seed_same_bytes_and_other_seeds_differ(renderer, small_pair, tmp_path):
    from drivingscene.data import save_frame_pair
    from drivingscene.synth.generate import generate_pair
    from drivingscene.synth.render import SynthRenderer

    again = generate_pair(SMALL, TEST_SEED, SynthRenderer())  # a fresh GL context too
    a = save_frame_pair(small_pair, tmp_path / "a.npz").read_bytes()
    b = save_frame_pair(again, tmp_path / "b.npz").read_bytes()
    assert a == b
    other = generate_pair(SMALL, TEST_SEED + 1, renderer)
    assert np.abs(other.images.astype(int) - small_pair.images).mean() > 10
    assert not np.array_equal(other.ego_to_world, small_pair.ego_to_world)
