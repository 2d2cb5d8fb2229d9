"""D's matching: the plane sweep lands where the rigid flow does, the compiled correlation equals
the torch path (values and gradients), and with no parallax D returns its monocular depth."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from drivingscene.data.tensors import pair_to_tensors
from drivingscene.geometry.camera import scale_intrinsics
from drivingscene.geometry.flow import rigid_flow
from drivingscene.models import DrivingSceneModel, ModelConfig
from drivingscene.models.depth import DepthConfig
from drivingscene.models.matching import (
    correlate,
    correlate_torch,
    plane_depths,
    sample_validity,
    sweep_coordinates,
    sweep_homographies,
    sweep_parallax,
    sweep_volume,
    target_rays,
)
from drivingscene.models.pipeline import matching_sources, predict_static, view_geometry
from tests.factories import make_pair

SMALL = ModelConfig(depth=DepthConfig(width=8, decoder_channels=(8, 8, 16, 16, 32), match_planes=8, match_channels=8))


def test_plane_depths_are_evenly_spaced_in_inverse_depth():
    depths = plane_depths(5, 1.0, 80.0)
    assert depths[0] == pytest.approx(1.0) and depths[-1] == pytest.approx(80.0)
    steps = (1.0 / depths).diff()
    torch.testing.assert_close(steps, steps[:1].expand_as(steps))


def test_sources_are_the_other_keyframe_and_the_neighbours():
    pair = make_pair(num_views=4, height=8, width=12)  # yaws 0, 90, 180, 270 degrees
    sources = matching_sources(torch.from_numpy(pair.cam_to_ego))
    assert sources.shape == (8, 3)
    assert sources[:, 0].tolist() == [4, 5, 6, 7, 0, 1, 2, 3]  # same camera, other keyframe
    assert sorted(sources[0, 1:].tolist()) == [1, 3] and sorted(sources[5, 1:].tolist()) == [4, 6]
    one = matching_sources(torch.from_numpy(make_pair(num_views=1).cam_to_ego))
    assert one.tolist() == [[1, -1, -1], [0, -1, -1]]
    two = matching_sources(torch.from_numpy(make_pair(num_views=2).cam_to_ego))
    assert two[:, 2].tolist() == [-1] * 4 and two[0, 1].item() == 1


def test_the_sweep_lands_where_the_rigid_flow_of_a_plane_does():
    pair = make_pair(num_views=3, height=10, width=14)
    batch = pair_to_tensors(pair)
    geometry = view_geometry(batch, batch.image_size)
    k = batch.intrinsics.repeat(2, 1, 1)
    depths = plane_depths(4, 2.0, 30.0)
    a, b, present = sweep_homographies(k, geometry)
    uv, z = sweep_coordinates(target_rays(k, 10, 14), a, b, depths)
    c2l = geometry.cam_to_local
    checked = 0
    for target, slot in [(0, 0), (2, 1), (4, 2)]:
        source = geometry.sources[target, slot]
        for p, d in enumerate(depths):
            flow, dst_z = rigid_flow(torch.full((10, 14), float(d)), k[target], c2l[target], c2l[source], k[source])
            grid = torch.stack(torch.meshgrid(torch.arange(14.0), torch.arange(10.0), indexing="xy"), -1)
            front = dst_z > 0.1  # behind the source camera the projection is meaningless
            checked += int(front.sum())
            torch.testing.assert_close(uv[target, slot, p][front], (grid + flow)[front], atol=1e-3, rtol=1e-4)
            torch.testing.assert_close(z[target, slot, p], dst_z, atol=1e-4, rtol=1e-4)
    assert present.all() and checked > 200


def _random_sweep(seed: int = 0):
    torch.manual_seed(seed)
    batch, slots, planes, height, width, channels = 4, 3, 5, 12, 20, 8
    features = torch.nn.functional.normalize(torch.randn(batch, channels, height, width), dim=1)
    sources = torch.tensor([[1, 2, -1], [0, 3, 2], [3, 0, 1], [2, 1, 0]])
    uv = torch.rand(batch, slots, planes, height, width, 2) * torch.tensor([width + 2.0, height + 2.0]) - 1
    valid = (uv[..., 0] >= 0) & (uv[..., 0] <= width - 1) & (uv[..., 1] >= 0) & (uv[..., 1] <= height - 1)
    valid &= torch.rand(batch, slots, planes, height, width) > 0.2
    valid[0, 2] = False  # no source there
    return features, sources, uv, valid


def test_correlation_is_the_cosine_with_the_sampled_source():
    features, sources, uv, valid = _random_sweep()
    cost = correlate_torch(features, sources, uv, valid)
    b, s, p, y, x = 1, 2, 3, 4, 5
    valid[b, s, p, y, x] = True
    uv[b, s, p, y, x] = torch.tensor([7.0, 9.0])  # on a pixel centre: no interpolation
    cost = correlate_torch(features, sources, uv, valid)
    expected = (features[b, :, y, x] * features[sources[b, s], :, 9, 7]).sum()
    torch.testing.assert_close(cost[b, s, p, y, x], expected)
    assert (cost[~valid] == 0).all() and cost.abs().max() <= 1 + 1e-5


def test_compiled_correlation_equals_the_torch_path_with_gradients(compiled_kernels):
    features, sources, uv, valid = _random_sweep(1)
    features.requires_grad_()
    reference = correlate_torch(features, sources, uv, valid)
    compiled = correlate(features, sources, uv, valid, backend="cpp")
    torch.testing.assert_close(compiled, reference, atol=1e-5, rtol=1e-5)
    weights = torch.randn_like(reference)
    (grad_reference,) = torch.autograd.grad((reference * weights).sum(), features)
    (grad_compiled,) = torch.autograd.grad((compiled * weights).sum(), features)
    torch.testing.assert_close(grad_compiled, grad_reference, atol=1e-5, rtol=1e-5)


def test_compiled_correlation_counts_taps_outside_the_image_as_zero(compiled_kernels):
    """Samples within one pixel outside the image, marked valid anyway: the compiled path pads with
    zeros as grid_sample does (and reads nothing outside the feature maps)."""
    features, sources, uv, _ = _random_sweep(2)
    valid = torch.ones(uv.shape[:-1], dtype=torch.bool)
    valid[0, 2] = False  # no source there
    reference = correlate_torch(features, sources, uv, valid)
    torch.testing.assert_close(correlate(features, sources, uv, valid, backend="cpp"), reference, atol=1e-5, rtol=1e-5)


def _stopped(pair):
    """The pair with the ego standing still (both keyframes at the same pose)."""
    ego = pair.ego_to_world.copy()
    ego[1] = ego[0]
    return replace(pair, ego_to_world=ego)


def test_with_no_parallax_depth_is_the_monocular_depth_exactly():
    torch.manual_seed(0)
    model = DrivingSceneModel(SMALL).eval()
    with torch.no_grad():  # a gate that would otherwise trust matching everywhere
        model.depth_net.matching.out.bias[-1] = 10.0
    pair = _stopped(make_pair(num_views=1, height=32, width=48))
    with torch.no_grad():
        out = predict_static(model, pair_to_tensors(pair)).depth_output
    assert not out.matching.informative.any() and (out.matching.gate == 0).all()
    for fused, mono in zip(out.depths, out.mono_depths):
        torch.testing.assert_close(fused, mono, atol=0, rtol=0)


def test_ego_stopped_leaves_only_the_neighbours_overlap_informative():
    pair = _stopped(make_pair(num_views=3, height=24, width=32))
    batch = pair_to_tensors(pair)
    geometry = view_geometry(batch, batch.image_size)
    k = batch.intrinsics.repeat(2, 1, 1)
    a, b, present = sweep_homographies(k, geometry)
    uv, z = sweep_coordinates(target_rays(k, 24, 32), a, b, plane_depths(16, 1.0, 80.0))
    valid = sample_validity(uv, z, present, geometry.sources, None)
    parallax = sweep_parallax(uv, valid)
    assert parallax[:, 0].max() < 1e-3  # the same camera at the same pose: no parallax anywhere
    moving = sweep_parallax(*_sweep_of(make_pair(num_views=3, height=24, width=32)))
    assert moving[:, 0].mean() > 1.0  # the ego moved 4 m: the temporal slot sweeps


def _sweep_of(pair):
    batch = pair_to_tensors(pair)
    geometry = view_geometry(batch, batch.image_size)
    k = batch.intrinsics.repeat(2, 1, 1)
    a, b, present = sweep_homographies(k, geometry)
    uv, z = sweep_coordinates(target_rays(k, *batch.image_size), a, b, plane_depths(16, 1.0, 80.0))
    return uv, sample_validity(uv, z, present, geometry.sources, None)


def test_masked_source_pixels_are_not_sampled():
    pair = make_pair(num_views=3, height=24, width=32)
    mask = np.ones((3, 24, 32), bool)
    mask[:, 12:] = False  # the lower half of every image is the ego's body
    batch = pair_to_tensors(replace(pair, valid_mask=mask))
    geometry = view_geometry(batch, batch.image_size)
    k = batch.intrinsics.repeat(2, 1, 1)
    a, b, present = sweep_homographies(k, geometry)
    uv, z = sweep_coordinates(target_rays(k, 24, 32), a, b, plane_depths(8, 1.0, 80.0))
    valid = sample_validity(uv, z, present, geometry.sources, geometry.valid)
    assert (uv[..., 1][valid].round() < 12).all()
    assert valid.any()


def test_depth_net_runs_on_any_rig_and_resizes_the_world_mask():
    torch.manual_seed(0)
    model = DrivingSceneModel(replace(SMALL, input_size=(32, 48))).eval()
    for views in (1, 2, 5):
        pair = make_pair(num_views=views, height=40, width=64)
        batch = pair_to_tensors(replace(pair, valid_mask=np.ones((views, 40, 64), bool)))
        with torch.no_grad():
            static = predict_static(model, batch)
        assert static.depth.shape == (2, views, 40, 64) and torch.isfinite(static.depth).all()
        assert static.depth_output.matching.gate.shape == (2 * views, 1, 16, 24)


def test_road_prior_is_the_ground_depth_below_the_horizon():
    model = DrivingSceneModel(SMALL)
    pair = make_pair(num_views=2, height=30, width=40)
    k = torch.from_numpy(pair.intrinsics)
    c2e = torch.from_numpy(pair.cam_to_ego)
    prior = model.depth_net.road_prior(k, c2e, 30, 40)
    assert prior.shape == (2, 2, 30, 40)
    # level cameras 1.5 m up: the ray of row v meets the road at z = f h / (v - cy)
    f, cy, height = float(k[0, 1, 1]), float(k[0, 1, 2]), float(c2e[0, 2, 3])
    row = 25
    ground = f * height / (row - cy)
    focal = float(k[0, 0, 0]) / 40 / model.config.depth.ref_focal
    assert prior[0, 0, row, 7].item() == pytest.approx(2.0 * focal / ground, rel=1e-4)
    assert (prior[:, 0, : int(cy)] == 0).all()  # above the horizon: no road
    assert (prior[:, 1, : int(cy)] > 0).all() and (prior[:, 1, int(cy) + 1 :] < 0).all()


def test_old_configs_load_as_monocular_depth_networks():
    config = ModelConfig.from_dict({"depth": {"width": 8}})
    assert config.depth.match_planes == 0 and config.depth.road_prior is False
    assert DrivingSceneModel(config).depth_net.matching is None


def test_intrinsics_scaling_is_applied_before_the_sweep():
    """The sweep at half resolution uses intrinsics scaled with the half-pixel rule."""
    k = torch.tensor([[[40.0, 0, 23.5], [0, 40.0, 15.5], [0, 0, 1]]])
    half = scale_intrinsics(k, 0.5, 0.5)
    rays = target_rays(half, 16, 24)
    torch.testing.assert_close(
        rays[0, 0, 0], torch.tensor([(0 - half[0, 0, 2]) / half[0, 0, 0], (0 - half[0, 1, 2]) / half[0, 1, 1], 1.0])
    )


def test_compiled_sweep_equals_the_torch_steps(compiled_kernels):
    torch.manual_seed(2)
    pair = make_pair(num_views=3, height=16, width=24)
    mask = np.ones((3, 16, 24), bool)
    mask[:, 11:, 4:20] = False  # an ego body at the bottom
    batch = pair_to_tensors(replace(pair, valid_mask=mask))
    geometry = view_geometry(batch, batch.image_size)
    k = batch.intrinsics.repeat(2, 1, 1)
    a, b, present = sweep_homographies(k, geometry)
    rays = target_rays(k, 16, 24)
    depths = plane_depths(12, 1.0, 80.0)
    features = torch.nn.functional.normalize(torch.randn(6, 8, 16, 24), dim=1)
    for valid in (None, geometry.valid):
        reference = sweep_volume(features, rays, a, b, present, geometry.sources, depths, valid, backend="torch")
        compiled = sweep_volume(features, rays, a, b, present, geometry.sources, depths, valid, backend="cpp")
        for got, want in zip(compiled, reference):
            torch.testing.assert_close(got, want, atol=1e-4, rtol=1e-4)
        assert reference[1].min() < 1 and reference[2].max() > 1  # some planes invalid, some parallax


def test_valid_slots_counts_the_valid_slots_per_plane():
    from drivingscene.models.matching import slot_mean, valid_slots

    torch.manual_seed(6)
    valid = torch.rand(2, 3, 4, 5, 6) > 0.4
    cost = torch.randn(2, 3, 4, 5, 6) * valid
    count = valid_slots(valid)
    assert count.dtype == torch.float32 and torch.equal(count, valid.float().sum(1))
    torch.testing.assert_close(slot_mean(cost, count), cost.sum(1) / valid.float().sum(1).clamp(min=1.0))
