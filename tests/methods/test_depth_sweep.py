"""The plane sweep that corrects depth before refinement (drivingscene/methods/depth_sweep.py)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from drivingscene.methods.depth_sweep import (
    PhotometricError,
    SweepConfig,
    corrected_depth,
    correction_field,
    cost_at,
    inverse_depths,
    neighbour_cameras,
    source_indices,
)
from drivingscene.methods.refine.inputs import refine_inputs
from drivingscene.models.losses import photometric_error
from tests.factories import make_rig

pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py


def _abs_rel(depth: torch.Tensor, gt: torch.Tensor) -> float:
    m = (gt > 0) & (gt < 80) & (depth > 0)
    return float(((depth - gt).abs() / gt)[m].mean())


def _correct(pair, prior, lidar=None, **kwargs):
    inputs = refine_inputs(pair)
    return corrected_depth(
        inputs.images,
        inputs.intrinsics,
        inputs.cam_to_local,
        inputs.cam_to_ego,
        prior,
        inputs.valid,
        lidar,
        SweepConfig(**kwargs),
    )


def test_photometric_error_is_l_loc_s():
    torch.manual_seed(0)
    x, y = torch.rand(3, 1, 20, 24), torch.rand(3, 1, 20, 24)
    torch.testing.assert_close(PhotometricError(y)(x), photometric_error(x, y))


def test_sources_are_the_other_keyframe_and_the_neighbours():
    _, cam_to_ego = make_rig(num_views=4)
    neighbours = neighbour_cameras(torch.from_numpy(cam_to_ego))
    assert sorted(neighbours[0]) == [1, 3]  # yaw 0 sits between yaw 90 and yaw 270
    sources = source_indices(4, neighbours)
    assert sources.shape == (5, 8)
    assert sources[0].tolist() == [4, 5, 6, 7, 0, 1, 2, 3]  # the same camera at the other keyframe
    assert source_indices(4, neighbours, "near").shape == (3, 8)
    assert source_indices(1, []).shape == (1, 2)
    q = inverse_depths(SweepConfig(near=2.0, far=100.0, hypotheses=5))
    assert q[0] == pytest.approx(0.5) and q[-1] == pytest.approx(0.01) and bool((q[1:] < q[:-1]).all())


def test_correction_field_goes_through_its_samples_and_fills_the_rest():
    log_ratio = torch.zeros(2, 30, 40)
    weight = torch.zeros(2, 30, 40)
    log_ratio[0, :, :20], log_ratio[0, :, 20:] = 1.0, -1.0
    weight[0, ::3, ::3] = 1.0  # sparse samples of a step
    field = correction_field(log_ratio, weight, (2.0, 8.0))
    assert float(field[0, 15, 5]) == pytest.approx(1.0, abs=1e-4) and float(field[0, 15, 35]) == pytest.approx(-1.0, abs=1e-4)
    assert float(field[1].abs().max()) == 0.0  # no samples: no correction


def test_sweep_finds_the_scale_of_a_depth_3x_too_near(synth_pair):
    gt = torch.from_numpy(synth_pair.gt_depth)
    near = gt * 0.33
    result = _correct(synth_pair, near, scale=1.0)
    assert int(result.corrected.sum()) >= 10  # of 12 images (a front camera may see too little parallax)
    assert _abs_rel(result.depth, gt) < 0.8 * _abs_rel(near, gt)
    m = gt > 0
    assert 0.7 < float((result.depth[m] / gt[m]).median()) < 1.4  # from 0.33: the scale is found
    assert bool((result.depth[gt <= 0] == 0).all())  # sky stays sky


def test_a_right_depth_is_left_alone(synth_pair):
    """The photometric arbitration keeps a right depth nearly as it is (the sweep's own noise would
    move it: every image corrected wholly), and without arbitration no image is triggered."""
    gt = torch.from_numpy(synth_pair.gt_depth)
    unarbitrated = _correct(synth_pair, gt, scale=1.0, trigger=1.0, arbitration=None)
    result = _correct(synth_pair, gt, scale=1.0)
    assert _abs_rel(result.depth, gt) < 0.2 * _abs_rel(unarbitrated.depth, gt)
    assert _abs_rel(result.depth, gt) < 0.1  # this small pair's sweep alone: AbsRel ~0.45
    triggered = _correct(synth_pair, gt, scale=1.0, arbitration=None)
    assert not bool(triggered.corrected.any()) and torch.equal(triggered.depth, gt)


def test_cost_volume_read_at_a_depth():
    config = SweepConfig(near=2.0, far=100.0, hypotheses=5)
    costs = torch.arange(5.0)[:, None, None, None].expand(5, 1, 2, 2).clone()  # cost = hypothesis index
    q = inverse_depths(config)
    depth = torch.tensor([[[1 / q[1], 1 / q[3]], [2 / (q[1] + q[2]), 1000.0]]])
    torch.testing.assert_close(cost_at(costs, depth, config), torch.tensor([[[1.0, 3.0], [1.5, 4.0]]]))


def test_lidar_returns_are_kept_and_spread(synth_pair):
    gt = torch.from_numpy(synth_pair.gt_depth)
    rng = np.random.default_rng(0)
    lidar = torch.where(torch.from_numpy(rng.uniform(size=gt.shape) < 0.1), gt, torch.zeros_like(gt))
    near = gt * 0.5
    result = _correct(replace(synth_pair, eval_images=None), near, lidar=lidar, scale=1.0)
    has = lidar > 0
    assert torch.equal(result.depth[has], lidar[has])
    assert _abs_rel(torch.where(has, 0 * gt, result.depth), gt) < 0.2  # pixels without a return follow them
    assert bool(result.corrected.all())
