"""Stereo across the rig (methods/cross_camera.py): overlapping cameras of one keyframe matched and
triangulated with their extrinsics."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from drivingscene.data.tensors import pair_to_tensors
from drivingscene.methods.cross_camera import CrossCameraConfig, cross_camera_depth, rig_triangulate
from drivingscene.models.lift import LiftConfig


def _camera(fx: float, width: int, height: int) -> np.ndarray:
    return np.array([[fx, 0, width / 2 - 0.5], [0, fx, height / 2 - 0.5], [0, 0, 1]], np.float64)


def _yaw(degrees: float, t: tuple[float, float, float]) -> np.ndarray:
    """Camera-axes (x right, y down, z forward) rotation about y, and a translation."""
    c, s = np.cos(np.radians(degrees)), np.sin(np.radians(degrees))
    out = np.eye(4)
    out[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    out[:3, 3] = t
    return out


def test_two_cameras_with_different_lenses_triangulate_the_true_depth():
    rng = np.random.default_rng(0)
    k_a, k_b = _camera(360.0, 320, 176), _camera(175.0, 320, 176)
    a_to_b = _yaw(-40.0, (0.8, 0.05, -0.3))
    z_true = rng.uniform(2.0, 60.0, 500)
    start = np.stack([rng.uniform(0, 319, 500), rng.uniform(0, 175, 500)], 1)
    points = np.concatenate([start, np.ones((500, 1))], 1) @ np.linalg.inv(k_a).T * z_true[:, None]
    there = points @ a_to_b[:3, :3].T + a_to_b[:3, 3]
    end = (there @ k_b.T)[:, :2] / there[:, 2:3]
    front = there[:, 2] > 0.5
    z, off_line, parallax = rig_triangulate(end.astype(np.float32), start.astype(np.float32), k_a, k_b, a_to_b)
    np.testing.assert_allclose(z[front], z_true[front], rtol=2e-3)
    assert off_line[front].max() < 1e-2
    # nearer points have more parallax (the baseline over the depth)
    order = np.argsort(z_true[front])
    assert parallax[front][order[:50]].mean() > 3 * parallax[front][order[-50:]].mean()
    # an end point moved across the epipolar line is off it by about as much
    normal = np.array([0.0, 1.0], np.float32)
    _, moved, _ = rig_triangulate((end + 3 * normal).astype(np.float32), start.astype(np.float32), k_a, k_b, a_to_b)
    assert np.median(moved[front]) > 0.5


def _inputs(pair, guide_scale: float = 1.0):
    batch = pair_to_tensors(pair, with_gt=False, with_eval=False)
    world = pair.gt_depth > 0
    guide = torch.from_numpy(np.where(world, pair.gt_depth * guide_scale, 50.0).astype(np.float32))
    return guide, torch.from_numpy(world), batch


def test_overlapping_cameras_triangulate_near_the_ground_truth(synth_pair):
    guide, world, batch = _inputs(synth_pair, 1.3)  # the guide 30 % too far
    z, parallax, pairs = cross_camera_depth(guide, world, synth_pair.images, batch, LiftConfig())
    got = (z > 0).numpy()
    gt = synth_pair.gt_depth
    assert pairs >= synth_pair.num_views  # every camera of the surround rig has a neighbour
    assert got.sum() > 0.02 * world.sum()
    assert not (got & ~world.numpy()).any()  # only world pixels
    rel = np.abs(z.numpy()[got] - gt[got]) / gt[got]
    assert np.median(rel) < 0.05 and rel.mean() < 0.1  # 0.046 mean measured; the guide alone is 0.3 off
    assert (parallax.numpy()[got] >= LiftConfig().epipolar_min_parallax).all()


def test_a_camera_alone_or_images_that_do_not_match_determine_nothing(synth_pair):
    guide, world, batch = _inputs(synth_pair)
    one = replace(synth_pair, images=synth_pair.images[:, :1], intrinsics=synth_pair.intrinsics[:1])
    one_batch = pair_to_tensors(
        replace(one, cam_to_ego=synth_pair.cam_to_ego[:1], gt_depth=None, valid_mask=None), with_gt=False, with_eval=False
    )
    z, _, pairs = cross_camera_depth(guide[:, :1], world[:, :1], one.images, one_batch, LiftConfig())
    assert pairs == 0 and not z.any()
    # noise instead of images: the matches neither agree both ways nor lie on the epipolar lines
    noise = np.random.default_rng(1).integers(0, 256, synth_pair.images.shape, dtype=np.uint8)
    z, _, _ = cross_camera_depth(guide, world, noise, batch, LiftConfig())
    real, _, _ = cross_camera_depth(guide, world, synth_pair.images, batch, LiftConfig())
    assert (z > 0).sum() < 0.3 * (real > 0).sum()


def test_a_stricter_overlap_matches_fewer_pairs_and_config_is_checked(synth_pair):
    guide, world, batch = _inputs(synth_pair)
    _, _, loose = cross_camera_depth(guide, world, synth_pair.images, batch, LiftConfig(), CrossCameraConfig(min_overlap=0.01))
    _, _, strict = cross_camera_depth(guide, world, synth_pair.images, batch, LiftConfig(), CrossCameraConfig(min_overlap=0.5))
    assert strict < loose
    for field, value in (("preset", "slow"), ("min_overlap", 0.0), ("margin", -1), ("consistency_px", 0.0)):
        with pytest.raises(ValueError, match=field):
            CrossCameraConfig(**{field: value})


def test_the_compiled_checks_and_triangulation_equal_the_numpy_path(synth_pair, compiled_kernels):
    guide, world, batch = _inputs(synth_pair, 1.3)
    z_cpp, parallax_cpp, _ = cross_camera_depth(guide, world, synth_pair.images, batch, LiftConfig(), backend="cpp")
    z_np, parallax_np, _ = cross_camera_depth(guide, world, synth_pair.images, batch, LiftConfig(), backend="torch")
    assert (z_cpp > 0).sum() > 100
    # the same pixels; the same depth and parallax up to float rounding
    assert torch.equal(z_cpp > 0, z_np > 0)
    torch.testing.assert_close(z_cpp, z_np, rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(parallax_cpp, parallax_np, rtol=1e-4, atol=1e-4)


def test_cameras_at_one_point_have_no_baseline_and_determine_nothing(synth_pair):
    """A rig whose cameras share one centre (rotations only) sees no parallax between them:
    nothing is triangulated, rather than noise."""
    cam_to_ego = synth_pair.cam_to_ego.copy()
    cam_to_ego[:, :3, 3] = cam_to_ego[0, :3, 3]
    pair = replace(synth_pair, cam_to_ego=cam_to_ego)
    guide, world, batch = _inputs(pair)
    z, _, pairs = cross_camera_depth(guide, world, pair.images, batch, LiftConfig())
    assert pairs > 0 and not z.any()
