"""Ground truth against independent recomputation from the file's own calibration and poses.

These would catch convention mistakes (half-pixel offsets, flipped rows, swapped poses, wrong
camera axes), not only shapes: each recomputation uses ``drivingscene.geometry`` and the stored
float32/float64 arrays, never the generator's internals.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from drivingscene.geometry import backward_warp, forward_backward_consistency, project, rigid_flow, unproject
from drivingscene.geometry.flow import cams_to_world
from drivingscene.geometry.se3 import interpolate_pose, transform_points

pytestmark = pytest.mark.gl


def _poses(pair):
    """Camera-to-world ``[2, V, 4, 4]`` float64 from the file's rig and ego poses."""
    return cams_to_world(torch.tensor(pair.cam_to_ego, dtype=torch.float64), torch.tensor(pair.ego_to_world))


def _rigid(pair, k: int, poses=None, intrinsics=None):
    poses = _poses(pair) if poses is None else poses
    k_mat = torch.tensor(pair.intrinsics, dtype=torch.float64) if intrinsics is None else intrinsics
    return rigid_flow(torch.tensor(pair.gt_depth[k], dtype=torch.float64), k_mat, poses[k], poses[1 - k])


def _static_error(pair, k: int, **kwargs) -> tuple[np.ndarray, float]:
    flow, z_other = _rigid(pair, k, **kwargs)
    static = (pair.gt_depth[k] > 0) & ~pair.gt_dynamic[k] & (z_other.numpy() > 0.5)
    err = np.linalg.norm(flow.numpy() - pair.gt_flow[k], axis=-1)[static]
    return err, float(static.mean())


@pytest.mark.parametrize("k", [0, 1])
def test_static_flow_is_rigid_flow_from_depth_and_poses(medium_pair, k):
    err, share = _static_error(medium_pair, k)
    assert share > 0.5
    assert np.median(err) <= 0.05
    assert np.percentile(err, 99) <= 0.5
    mags = np.linalg.norm(medium_pair.gt_flow[k], axis=-1)
    assert np.median(mags) > 2.0  # a real test: the flow is far from zero


def test_rigid_flow_check_catches_convention_mistakes(medium_pair):
    """The same check with swapped ego poses or a half-pixel principal point fails clearly."""
    poses = _poses(medium_pair)
    swapped, _ = _static_error(medium_pair, 0, poses=poses.flip(0))
    assert np.median(swapped) > 1.0
    k_shift = torch.tensor(medium_pair.intrinsics, dtype=torch.float64)
    k_shift[:, :2, 2] += 0.5
    shifted, _ = _static_error(medium_pair, 0, intrinsics=k_shift)
    assert np.median(shifted) > 0.05


def _psnr(a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor) -> float:
    mse = (a - b).square().mean(1)[mask].mean().item()
    return 10 * np.log10(1 / mse)


def test_backward_warp_with_gt_flow_reproduces_keyframe_0(medium_pair):
    images = torch.tensor(medium_pair.images, dtype=torch.float32).permute(0, 1, 4, 2, 3) / 255
    flow_fw, flow_bw = torch.tensor(medium_pair.gt_flow[0]), torch.tensor(medium_pair.gt_flow[1])
    consistent = forward_backward_consistency(flow_fw, flow_bw)
    warped, inside = backward_warp(images[1], flow_fw)
    mask = consistent & inside
    assert mask.float().mean() > 0.25
    assert _psnr(warped, images[0], mask) >= 25.0
    unwarped, _ = backward_warp(images[1], torch.zeros_like(flow_fw))
    assert _psnr(unwarped, images[0], mask) < 20.0  # the flow, not the scene, makes them agree


@pytest.mark.parametrize("k", [0, 1])
def test_scene_flow_moves_points_onto_the_flow(medium_pair, k):
    poses = _poses(medium_pair)
    depth = torch.tensor(medium_pair.gt_depth[k], dtype=torch.float64)
    k_mat = torch.tensor(medium_pair.intrinsics, dtype=torch.float64)
    world = transform_points(poses[k], unproject(depth, k_mat).flatten(1, 2))
    moved = world + torch.tensor(medium_pair.gt_scene_flow[k], dtype=torch.float64).flatten(1, 2)
    cam = transform_points(torch.linalg.inv(poses[1 - k]), moved)
    uv, z = project(cam, k_mat)
    h, w = medium_pair.image_size
    grid = torch.stack(torch.meshgrid(torch.arange(w), torch.arange(h), indexing="xy"), -1).reshape(-1, 2)
    target = grid + torch.tensor(medium_pair.gt_flow[k], dtype=torch.float64).flatten(1, 2)
    valid = (depth.flatten(1) > 0) & (z > 0.5)
    err = (uv - target).norm(dim=-1)[valid]
    assert err.median() <= 0.01 and torch.quantile(err, 0.99) <= 0.2
    dynamic = torch.tensor(medium_pair.gt_dynamic[k]).flatten(1) & valid
    assert dynamic.sum() > 100  # moving objects are in view, so the scene flow term is exercised


def test_static_scene_flow_is_zero_and_moving_objects_move(medium_pair):
    flow3 = np.linalg.norm(medium_pair.gt_scene_flow, axis=-1)
    assert np.all(flow3[~medium_pair.gt_dynamic] == 0)
    assert medium_pair.gt_dynamic.mean() > 0.005
    assert np.min(flow3[medium_pair.gt_dynamic]) > 0.2  # slowest walker: 0.9 m/s x 0.5 s x 0.5
    assert not np.any(medium_pair.gt_dynamic & (medium_pair.gt_depth == 0))


def test_sky_is_depth_zero_with_rotation_only_flow(medium_pair):
    poses = _poses(medium_pair).numpy()
    k_mat = medium_pair.intrinsics.astype(np.float64)
    sky = medium_pair.gt_depth[0] == 0
    assert sky[0].mean() > 0.01  # CAM_FRONT sees sky
    h, w = medium_pair.image_size
    v, u = np.nonzero(sky[0])
    rays = np.linalg.inv(k_mat[0]) @ np.stack([u, v, np.ones_like(u)]).astype(np.float64)
    rot = poses[1, 0, :3, :3].T @ poses[0, 0, :3, :3]
    p = k_mat[0] @ (rot @ rays)
    expected = (p[:2] / p[2]).T - np.stack([u, v], -1)
    np.testing.assert_allclose(medium_pair.gt_flow[0, 0][v, u], expected, atol=1e-3)
    assert np.all(medium_pair.gt_scene_flow[0][sky] == 0)


def test_ego_path_eval_frames_and_world_offset(medium_pair):
    pair = medium_pair
    t0, t1 = pair.timestamps
    assert t0 > 1.0 and t1 - t0 == pytest.approx(0.5)
    assert np.linalg.norm(pair.ego_to_world[0, :3, 3]) > 10  # world origin is not at the ego
    rel = np.linalg.inv(pair.ego_to_world[0]) @ pair.ego_to_world[1]
    assert np.linalg.norm(rel[:3, 3]) == pytest.approx(8.0 * 0.5, abs=0.01)  # chord of a gentle arc
    yaw = np.degrees(np.arctan2(rel[1, 0], rel[0, 0]))
    assert 0.2 < abs(yaw) < 5  # a curved road: rotation between keyframes is non-trivial
    np.testing.assert_allclose(pair.eval_timestamps, [t0 + 0.25])
    mid = interpolate_pose(torch.tensor(pair.ego_to_world[0]), torch.tensor(pair.ego_to_world[1]), 0.5).numpy()
    np.testing.assert_allclose(pair.eval_ego_to_world[0, :3, :3], mid[:3, :3], atol=1e-9)
    # on the arc, not on the chord: the midpoint lies off the straight line by the sagitta
    offset = np.linalg.norm(pair.eval_ego_to_world[0, :3, 3] - mid[:3, 3])
    assert 1e-5 < offset < 0.05
    assert pair.eval_dynamic.shape == (1, 6, *pair.image_size) and pair.eval_dynamic.any()


def test_saved_file_is_valid_and_round_trips(medium_pair, tmp_path):
    from drivingscene.data import load_frame_pair, save_frame_pair, validate_frame_pair_file

    path = save_frame_pair(medium_pair, tmp_path / "pair.npz")
    assert validate_frame_pair_file(path) == []
    loaded = load_frame_pair(path)
    np.testing.assert_array_equal(loaded.gt_flow, medium_pair.gt_flow)
    assert loaded.camera_names == medium_pair.camera_names


def test_bench_motion_separates_non_rigid_motion(medium_pair):
    """`bench motion`'s non-rigid part (flow minus the pipeline's rigid flow of the true depth)
    vanishes on static pixels and not on moving ones."""
    from dataclasses import replace

    from drivingscene.bench.motion import moving_pixel_motion

    static = replace(medium_pair, gt_dynamic=~medium_pair.gt_dynamic)
    flow, nonrigid, off, _, _ = moving_pixel_motion(static)
    assert np.median(flow) > 2.0 and np.median(nonrigid) < 0.05 and np.median(off) < 0.05
    flow, nonrigid, off, cams, _ = moving_pixel_motion(medium_pair)
    assert len(cams) > 100 and np.median(nonrigid) > 2.0
