"""Randomised pairs: the exact ground truth on a random rig with staggered camera triggers, the
ego-body mask, photometric jitter, and the randomised preset.

The ground-truth checks recompute from the file's own arrays (``geometry`` and each image's
``camera_ego_to_world``), as ``test_ground_truth`` does for the fixed rig.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from drivingscene.geometry import backward_warp, forward_backward_consistency, project, rigid_flow, unproject
from drivingscene.geometry.se3 import transform_points
from drivingscene.synth.config import SynthConfig, resolve_config

pytestmark = pytest.mark.gl

SEED = 200011
# random rig, staggered triggers (0.1 s: 1.2 m of ego travel at 12 m/s), a suburb or a town
RANDOM_GT = SynthConfig(
    height=64, width=112, rig="random", capture_spread=0.1, ego_speed=12.0, scene_style="mixed", lighting="varied"
)
SMALL = SynthConfig(height=48, width=88)


@pytest.fixture(scope="module")
def random_pair(generate):
    return generate(RANDOM_GT, SEED)


def _image_poses(pair) -> torch.Tensor:
    """``[2, V, 4, 4]`` camera-to-world of every keyframe image at its own capture."""
    return torch.tensor(pair.camera_ego_poses()) @ torch.tensor(pair.cam_to_ego, dtype=torch.float64)[None]


def test_random_rig_pair_is_valid_with_per_image_capture(random_pair):
    pair = random_pair
    assert pair.validate() == [] and 5 <= pair.num_views <= 8
    assert pair.camera_names == tuple(f"CAM_{i}" for i in range(pair.num_views))
    offsets = pair.camera_timestamps - pair.timestamps[:, None]
    np.testing.assert_allclose(offsets[1], offsets[0], atol=1e-9)  # the trigger pattern repeats every frame
    np.testing.assert_allclose(pair.eval_camera_timestamps - pair.eval_timestamps[:, None], offsets[:1], atol=1e-9)
    assert 0.05 < np.ptp(offsets[0]) <= 0.1 and np.all(np.abs(offsets) <= 0.05)
    step = np.linalg.norm(pair.camera_ego_to_world[0, :, :3, 3] - pair.ego_to_world[0, :3, 3], axis=-1)
    np.testing.assert_allclose(step, 12.0 * np.abs(offsets[0]), rtol=1e-3)  # where the ego was at each trigger


@pytest.mark.parametrize("k", [0, 1])
def test_static_flow_is_rigid_flow_between_the_two_captures(random_pair, k):
    pair, poses = random_pair, _image_poses(random_pair)
    k_mat = torch.tensor(pair.intrinsics, dtype=torch.float64)
    flow, z_other = rigid_flow(torch.tensor(pair.gt_depth[k], dtype=torch.float64), k_mat, poses[k], poses[1 - k])
    static = (pair.gt_depth[k] > 0) & ~pair.gt_dynamic[k] & (z_other.numpy() > 0.5)
    err = np.linalg.norm(flow.numpy() - pair.gt_flow[k], axis=-1)[static]
    assert static.mean() > 0.4 and np.median(err) <= 0.05 and np.percentile(err, 99) <= 0.5
    assert np.median(np.linalg.norm(pair.gt_flow[k], axis=-1)) > 1.0


@pytest.mark.parametrize("k", [0, 1])
def test_scene_flow_moves_points_onto_the_flow(random_pair, k):
    pair, poses = random_pair, _image_poses(random_pair)
    depth = torch.tensor(pair.gt_depth[k], dtype=torch.float64)
    k_mat = torch.tensor(pair.intrinsics, dtype=torch.float64)
    world = transform_points(poses[k], unproject(depth, k_mat).flatten(1, 2))
    moved = world + torch.tensor(pair.gt_scene_flow[k], dtype=torch.float64).flatten(1, 2)
    uv, z = project(transform_points(torch.linalg.inv(poses[1 - k]), moved), k_mat)
    h, w = pair.image_size
    grid = torch.stack(torch.meshgrid(torch.arange(w), torch.arange(h), indexing="xy"), -1).reshape(-1, 2)
    target = grid + torch.tensor(pair.gt_flow[k], dtype=torch.float64).flatten(1, 2)
    valid = (depth.flatten(1) > 0) & (z > 0.5)
    err = (uv - target).norm(dim=-1)[valid]
    assert err.median() <= 0.01 and torch.quantile(err, 0.99) <= 0.2
    assert (torch.tensor(pair.gt_dynamic[k]).flatten(1) & valid).sum() > 20  # moving objects exercise it


def test_each_image_is_rendered_at_its_own_capture(random_pair, renderer):
    """Re-render the static world from the file's per-image poses: the depth matches exactly; from
    the keyframe's single pose it does not (the triggers are up to 1.2 m of travel apart)."""
    from drivingscene.synth.render import View
    from drivingscene.synth.scene import build_scene

    pair, scene = random_pair, build_scene(RANDOM_GT, SEED)
    cam_to_ego = pair.cam_to_ego.astype(np.float64)
    gpu = renderer.upload(scene.static_vertices, [])
    try:
        views = [
            View(poses @ cam_to_ego, scene.road_to_world, np.zeros((0, 4, 4)))
            for poses in (pair.camera_ego_poses()[0], pair.ego_to_world[0][None])
        ]
        depths = [
            renderer.render_geometry(gpu, v, v, pair.intrinsics.astype(np.float64), pair.image_size)[0][..., 2] for v in views
        ]
    finally:
        gpu.release()
    static = (pair.gt_depth[0] > 0) & ~pair.gt_dynamic[0]
    own, keyframe = (np.abs(d - pair.gt_depth[0])[static] / pair.gt_depth[0][static] for d in depths)
    assert np.mean(own > 1e-5) < 0.001
    assert np.mean(keyframe > 1e-3) > 0.15


def test_backward_warp_with_gt_flow_on_a_random_rig(random_pair):
    images = torch.tensor(random_pair.images, dtype=torch.float32).permute(0, 1, 4, 2, 3) / 255
    flow_fw, flow_bw = torch.tensor(random_pair.gt_flow[0]), torch.tensor(random_pair.gt_flow[1])
    mask = forward_backward_consistency(flow_fw, flow_bw) & backward_warp(images[1], flow_fw)[1]
    warped, _ = backward_warp(images[1], flow_fw)
    mse = (warped - images[0]).square().mean(1)[mask].mean().item()
    still = (images[1] - images[0]).square().mean(1)[mask].mean().item()
    assert mask.float().mean() > 0.25 and 10 * np.log10(1 / mse) >= 22.0 and still > 3 * mse


def test_ego_body_mask_and_kept_ground_truth(generate):
    plain = generate(replace(SMALL, rig="ddad"), SEED)
    body = generate(replace(SMALL, rig="ddad", ego_body=1.0), SEED)
    assert plain.valid_mask is None and body.valid_mask.shape == (6, 48, 88)
    masked = 1 - body.valid_mask.mean(axis=(1, 2))
    assert np.all((masked > 0.02) & (masked < 0.45)) and 0.05 < masked.mean() < 0.3
    np.testing.assert_array_equal(body.gt_depth, plain.gt_depth)  # the world's ground truth under the body
    np.testing.assert_array_equal(body.gt_flow, plain.gt_flow)
    outside = body.valid_mask[None, :, :, :, None] & np.ones((2, 1, 1, 1, 3), bool)
    np.testing.assert_array_equal(body.images[outside], plain.images[outside])
    assert np.abs(body.images.astype(int) - plain.images)[~outside].mean() > 5
    again = generate(replace(SMALL, rig="ddad", ego_body=0.5), SEED)
    assert again.valid_mask is None or 0 < (~again.valid_mask).any(axis=(1, 2)).sum() < 6


def test_photometric_jitter_is_deterministic_and_leaves_ground_truth(generate, renderer):
    from drivingscene.synth.generate import generate_pair

    config = replace(SMALL, photometric=1.0)
    jittered, plain = generate(config, SEED), generate(SMALL, SEED)
    np.testing.assert_array_equal(generate_pair(config, SEED, renderer).images, jittered.images)
    np.testing.assert_array_equal(jittered.gt_depth, plain.gt_depth)
    ratio = jittered.images.mean(axis=(2, 3, 4)) / plain.images.mean(axis=(2, 3, 4))  # [2, V]
    assert ratio[0].std() > 0.03  # each camera has its own look
    assert np.abs(ratio[1] - ratio[0]).max() < 0.08  # and keeps it from frame to frame
    other = generate(config, SEED + 1)
    assert not np.allclose(other.images.mean(axis=(2, 3, 4)) / generate(SMALL, SEED + 1).images.mean(axis=(2, 3, 4)), ratio)


def test_blackout_by_name_or_index_on_other_rigs(generate):
    pair = generate(replace(SMALL, rig="random", blackout_camera="2"), SEED)
    assert not pair.images[:, 2].any() and pair.images[:, 1].any()
    pair = generate(replace(SMALL, rig="ddad", blackout_camera="CAMERA_09"), SEED)
    assert not pair.images[:, 3].any()


def test_randomised_preset_pair(generate):
    config = resolve_config("randomised", height=48, width=88)
    assert (config.rig, config.scene_style, config.lighting, config.randomise_motion) == ("random", "mixed", "varied", True)
    pair = generate(config, SEED + 2)
    assert pair.validate() == [] and pair.camera_timestamps is not None
    assert pair.timestamps[1] - pair.timestamps[0] <= 0.6
