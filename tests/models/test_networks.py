"""D, P, R: shapes for any rig size, documented initial behaviour, focal scaling, gradients."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch
import torch.nn.functional as F

from drivingscene.data.tensors import pair_to_tensors
from drivingscene.gaussians.assembly import surfel_frames
from drivingscene.geometry.camera import pixel_grid
from drivingscene.models import DrivingSceneModel, ModelConfig
from drivingscene.models.depth import DepthConfig
from drivingscene.models.lift import LiftConfig, lift_scene_flow, sky_mask
from drivingscene.models.pipeline import (
    assemble,
    predict_depth,
    predict_flow,
    predict_static,
    rigid_flows,
    rigid_flows_and_behind,
)
from drivingscene.models.residual_flow import CameraDecoder, FlowConfig, ResidualFlowNet, decoder_slots, local_cost_volume
from tests.factories import make_pair, make_rig

SMALL = ModelConfig(depth=DepthConfig(width=8, decoder_channels=(8, 8, 16, 16, 32)))


@pytest.fixture(scope="module")
def model():
    torch.manual_seed(0)
    return DrivingSceneModel(SMALL).eval()


@pytest.mark.parametrize("height, width", [(32, 48), (30, 50)])
def test_static_shapes_for_odd_sizes(model, height, width):
    images = torch.rand(3, 3, height, width)
    k = torch.tensor([[40.0, 0, width / 2], [0, 40.0, height / 2], [0, 0, 1]]).expand(3, 3, 3)
    depth, params = model.static(images, k)
    assert depth.depth.shape == (3, height, width)
    assert [d.shape[-2:] == (height, width) for d in depth.depths] == [True] * 4
    assert params.log_scales.shape == (3, height, width, 3) and params.sh.shape == (3, height, width, 1, 3)
    assert (depth.depth > 0).all()


@pytest.mark.parametrize("input_size", [None, (24, 40)])
def test_d_alone_gives_the_depth_of_both_networks(input_size):
    """Test-time adaptation runs D alone (`predict_depth`): the same depth as `predict_static`'s,
    at the images' size and through a smaller network input size."""
    torch.manual_seed(0)
    net = DrivingSceneModel(replace(SMALL, input_size=input_size)).eval()
    batch = pair_to_tensors(make_pair(num_views=3, height=32, width=48), with_gt=False, with_eval=False)
    with torch.no_grad():
        expected = predict_static(net, batch).depth
        depth = predict_depth(net, batch)
    assert depth.shape == (2, 3, 32, 48)
    torch.testing.assert_close(depth, expected, rtol=0, atol=0)


def test_depth_scales_with_normalised_focal_length(model):
    images = torch.rand(1, 3, 32, 48).expand(2, -1, -1, -1)
    k = torch.tensor([[40.0, 0, 24], [0, 40.0, 16], [0, 0, 1]]).repeat(2, 1, 1)
    k[1, 0, 0] = 80.0  # twice the focal length: same pixels, twice the depth
    depth = model.depth_net(images, k).depth
    torch.testing.assert_close(depth[1], 2 * depth[0])


def test_gaussian_head_starts_at_surfels_with_pixel_colours(model):
    images = torch.rand(2, 3, 32, 48)
    k = torch.tensor([[40.0, 0, 24], [0, 40.0, 16], [0, 0, 1]]).expand(2, 3, 3)
    depth, params = model.static(images, k)
    quats, log_scales = surfel_frames(depth.depth, k)
    torch.testing.assert_close(params.log_scales, log_scales)
    torch.testing.assert_close(params.quats, quats)
    rgb = params.sh[..., 0, :] * 0.28209479177387814 + 0.5
    torch.testing.assert_close(rgb, images.permute(0, 2, 3, 1), atol=1e-5, rtol=0)
    assert torch.sigmoid(params.opacity_logits).min() > 0.9


def test_camera_slots_follow_viewing_yaw():
    _, rig = make_rig(num_views=6)  # yaws 0, 60, 120, 180, 240, 300 degrees
    slots = decoder_slots(torch.from_numpy(rig), (0.0, -55.0, -110.0, 180.0, 110.0, 55.0))
    assert slots.tolist() == [0, 5, 4, 3, 2, 1]
    _, two = make_rig(num_views=2)  # a front and a back camera
    assert decoder_slots(torch.from_numpy(two), (0.0, -55.0, -110.0, 180.0, 110.0, 55.0)).tolist() == [0, 3]


def test_cost_volume_peaks_at_the_true_shift():
    target = torch.randn(1, 8, 12, 16)
    source = torch.roll(target, shifts=(1, -2), dims=(2, 3))  # source(p) = target(p - (1, -2))
    cost = local_cost_volume(target, source, radius=3)
    best = cost[0, :, 4:-4, 4:-4].mean(dim=(1, 2)).argmax().item()
    dy, dx = divmod(best, 7)
    assert (dy - 3, dx - 3) == (1, -2)


def test_compiled_cost_volume_matches_the_torch_path_and_gradients_keep_torch(compiled_kernels):
    g = torch.Generator().manual_seed(3)
    target, source = torch.randn(2, 5, 9, 13, generator=g), torch.randn(2, 5, 9, 13, generator=g)
    with torch.no_grad():
        fast = local_cost_volume(target, source, 2)  # no gradients: the compiled kernel
    reference = local_cost_volume(target.requires_grad_(), source, 2)  # gradients: the torch path
    assert reference.grad_fn is not None and fast.shape == reference.shape == (2, 25, 9, 13)
    torch.testing.assert_close(fast, reference.detach(), atol=1e-6, rtol=1e-5)


def test_residual_flow_can_stop_at_a_coarser_level(model):
    """R refined down to 1/4 gives the flow its full run has at that level; all_levels=False
    keeps only the finest computed level."""
    torch.manual_seed(1)
    flow_net = ResidualFlowNet(FlowConfig()).eval()
    for p in flow_net.parameters():  # non-zero updates at every level
        p.data.normal_(0, 0.05)
    images = torch.rand(3, 3, 32, 48)
    rigid = torch.randn(3, 2, 32, 48)
    slots = torch.tensor([0, 1, 0])
    with torch.no_grad():
        full = flow_net(images, images.flip(0), rigid, slots)
        coarse = flow_net(images, images.flip(0), rigid, slots, finest_level=1)
        last = flow_net(images, images.flip(0), rigid, slots, finest_level=1, all_levels=False)
    assert len(full) == 4 and len(coarse) == 3 and len(last) == 1
    torch.testing.assert_close(coarse[-1], full[-2])
    torch.testing.assert_close(last[0], full[-2])
    assert (full[-1] - full[-2]).abs().max() > 1e-3  # the finest level does change the flow
    with pytest.raises(ValueError, match="finest_level"):
        flow_net(images, images.flip(0), rigid, slots, finest_level=4)


def test_replicate_conv_equals_torch_replicate_padding_conv():
    from drivingscene.models.blocks import ReplicateConv3x3

    torch.manual_seed(3)
    conv = ReplicateConv3x3(5, 4)
    reference = torch.nn.Conv2d(5, 4, 3, padding=1, padding_mode="replicate")
    reference.load_state_dict(conv.state_dict())
    for shape in ((2, 5, 7, 9), (1, 5, 1, 1)):
        x = torch.randn(shape).contiguous(memory_format=torch.channels_last)
        assert torch.equal(conv(x), reference(x))


@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16])
@pytest.mark.parametrize("channels_last", [False, True])
def test_replicate_pad_equals_torch_and_keeps_gradients_and_layout(dtype, channels_last):
    from drivingscene.models.blocks import replicate_pad1

    torch.manual_seed(4)
    x = torch.randn(2, 3, 5, 6).to(dtype)
    if channels_last:
        x = x.contiguous(memory_format=torch.channels_last)
    x.requires_grad_(True)
    reference = x.detach().clone().requires_grad_(True)
    out, expected = replicate_pad1(x), F.pad(reference.float(), (1, 1, 1, 1), mode="replicate").to(dtype)
    assert torch.equal(out, expected)
    assert out.is_contiguous(memory_format=torch.channels_last if channels_last else torch.contiguous_format)
    weight = torch.randn(out.shape).to(dtype)
    (out.float() * weight.float()).sum().backward()
    (expected.float() * weight.float()).sum().backward()
    # edge pixels collect the gradients of their copies (corners: three, summed in another order)
    tolerance = 1e-6 if dtype == torch.float32 else 2e-2
    assert torch.allclose(x.grad.float(), reference.grad.float(), atol=tolerance, rtol=tolerance)


@pytest.mark.parametrize("autocast", [False, True])
def test_conv_input_is_the_concatenation_in_the_layout_and_dtype_the_convolution_reads(autocast):
    from drivingscene.models.blocks import conv_input

    torch.manual_seed(5)
    parts = [
        torch.randn(2, 4, 5, 6).to(torch.bfloat16).contiguous(memory_format=torch.channels_last),  # a network's features
        torch.randn(2, 3, 5, 6),  # float32, NCHW: an image
        torch.randn(2, 1, 5, 6, requires_grad=True),  # one channel: log depth
    ]
    weight = torch.randn(7, 8, 3, 3)
    with torch.autocast("cpu", dtype=torch.bfloat16, enabled=autocast):
        x = conv_input(parts)
        # what the convolution computes in: its input as autocast casts it, or the promoted dtype
        expected = torch.cat([p.float() for p in parts], dim=1).to(torch.bfloat16 if autocast else torch.float32)
        assert x.dtype == expected.dtype and torch.equal(x, expected)
        assert x.is_contiguous(memory_format=torch.channels_last) and not x.is_contiguous()
        out = F.conv2d(x, weight, padding=1)
        reference = F.conv2d(torch.cat(parts, dim=1), weight, padding=1)
    torch.testing.assert_close(out.float(), reference.float(), atol=0.05 if autocast else 1e-5, rtol=0.02 if autocast else 1e-5)
    out.float().sum().backward()  # the gradient reaches the parts through the copies
    assert parts[2].grad is not None and parts[2].grad.abs().sum() > 0


def test_coarse_radius_widens_only_the_coarsest_cost_volume():
    wide = CameraDecoder(FlowConfig(radius=3, coarse_radius=6))
    assert FlowConfig(radius=3, coarse_radius=6).level_radii == [3, 3, 3, 6]
    assert [lvl.body[0].in_channels for lvl in wide.levels] == [
        lvl.body[0].in_channels + (13**2 - 7**2) * (i == 3) for i, lvl in enumerate(CameraDecoder(FlowConfig()).levels)
    ]


def test_hypotheses_add_cost_volumes_around_scaled_rigid_flow():
    torch.manual_seed(0)
    net = ResidualFlowNet(FlowConfig(channels=(8, 8, 8, 8), hidden=8, hypotheses=(1.0, 0.0))).eval()
    inputs = []
    net.decoders[0].levels[3].register_forward_hook(lambda module, args, out: inputs.append(args[0]))
    target, source = torch.rand(1, 3, 64, 96), torch.rand(1, 3, 64, 96)
    slots = torch.tensor([0])
    with torch.no_grad():
        for shift in (0.0, 40.0):  # no rigid motion, then a large one (a near object, static assumed)
            net(source, target, torch.full((1, 2, 64, 96), shift), slots, source=source)
    volume = 7 * 7
    rigid_centred = [x[:, :volume] for x in inputs]
    zero_centred = [x[:, volume : 2 * volume] for x in inputs]
    torch.testing.assert_close(zero_centred[0], zero_centred[1])  # does not follow the rigid flow
    assert not torch.allclose(rigid_centred[0], rigid_centred[1])  # follows it
    torch.testing.assert_close(rigid_centred[0], zero_centred[0])  # the same hypothesis when rigid is 0
    with pytest.raises(ValueError, match="unwarped source"):
        net(source, target, torch.zeros(1, 2, 64, 96), slots)


def test_scale_flow_turns_the_rigid_flow_off_with_one_number():
    """A coarsest-level scale of 0 (bias -1 on the scale output) gives residual = -rigid, i.e. a
    total flow of 0, at every output level; the untrained refinements add nothing."""
    net = ResidualFlowNet(FlowConfig(channels=(8, 8, 8, 8), hidden=8, hypotheses=(1.0, 0.0), scale_flow=True)).eval()
    image = torch.rand(1, 3, 64, 96)
    rigid = torch.tensor([30.0, -12.0]).view(1, 2, 1, 1).expand(1, 2, 64, 96)
    slots = torch.tensor([0])
    with torch.no_grad():
        assert all(r.abs().max() == 0 for r in net(image, image, rigid, slots, source=image))  # starts at 0
        net.decoders[0].levels[3].flow.bias[2] = -1.0
        residuals = net(image, image, rigid, slots, source=image)
    for residual in residuals:
        torch.testing.assert_close(residual, -rigid)


def test_configs_saved_before_the_search_options_load_the_same_network():
    old = ModelConfig().to_dict()
    for key in ("coarse_radius", "hypotheses", "scale_flow"):
        del old["flow"][key]
    config = ModelConfig.from_dict(old)  # weights trained before the fields existed
    assert config.flow.level_radii == [config.flow.radius] * len(config.flow.channels)
    assert config.flow.hypotheses == (1.0,) and not config.flow.scale_flow and not config.flow.own_source


def test_residual_flow_starts_at_zero_and_gets_gradients(model):
    pair = make_pair(num_views=3, height=32, width=48)
    batch = pair_to_tensors(pair)
    static = predict_static(model, batch)
    flow = predict_flow(model, batch, static.depth)
    assert flow.residual.shape == (2, 3, 32, 48, 2) and flow.residual.abs().max() == 0
    model.train()
    flow = predict_flow(model, batch, static.depth.detach())
    (flow.total.square().mean() + flow.residuals[0].mean()).backward()
    grads = [p.grad for p in model.flow_net.parameters() if p.grad is not None]
    assert grads and any(g.abs().sum() > 0 for g in grads)
    model.zero_grad()
    model.eval()


def test_assembly_excludes_sky_and_counts_pixels(model):
    pair = make_pair(num_views=2, height=32, width=48)
    batch = pair_to_tensors(pair)
    static = predict_static(model, batch)
    sky = sky_mask(static.depth, batch.intrinsics, model.config.depth.ref_focal, LiftConfig(sky_depth=math.inf))
    g = assemble(static, batch, sky)
    assert len(g) == 2 * 2 * 32 * 48
    sky[0, 0, :10] = True
    assert len(assemble(static, batch, sky)) == 2 * 2 * 32 * 48 - 10 * 48
    # Built in the world frame directly == built locally, then transformed (flows rotate too).
    yaw = 0.8
    to_world = torch.eye(4, dtype=torch.float64)
    to_world[:2, :2] = torch.tensor([[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]])
    to_world[:3, 3] = torch.tensor([50.0, -20.0, 1.0])
    flows = torch.randn(2, 2, 32, 48, 3)
    local = assemble(static, batch, sky, flows).transform(to_world)
    world = assemble(static, batch, sky, flows, local_to_world=to_world)
    for name in ("means", "flows", "quats", "log_scales", "sh", "opacity_logits"):
        torch.testing.assert_close(getattr(world, name), getattr(local, name), atol=1e-4, rtol=1e-5)


def test_compiled_activation_matches_the_torch_path(model, compiled_kernels):
    """The Gaussian head's activation without gradients (one compiled pass) equals the torch
    path, for SH degree 0 and 1; with gradients the torch path runs."""
    from drivingscene.models.gaussian_head import GaussianHead, GaussianHeadConfig

    g = torch.Generator().manual_seed(2)
    depth = 2 + 50 * torch.rand(3, 6, 8, generator=g).repeat_interleave(5, 1).repeat_interleave(5, 2)
    intrinsics = torch.tensor([[40.0, 0.2, 19.5], [0, 38.0, 14.5], [0, 0, 1]]).repeat(3, 1, 1)
    images = torch.rand(3, 3, 30, 40, generator=g)
    for degree in (0, 1):
        head = GaussianHead((8, 8, 16, 16, 32), 8, GaussianHeadConfig(sh_degree=degree))
        raw = 2 * torch.randn(3, 30, 40, head.num_out, generator=g)
        with torch.no_grad():
            fast = head.activate(raw, images, depth, intrinsics)
        slow = head.activate(raw.requires_grad_(), images, depth, intrinsics)
        assert slow.sh.grad_fn is not None
        for name in ("log_scales", "quats", "opacity_logits", "sh"):
            a, b = getattr(fast, name), getattr(slow, name).detach()
            assert a.shape == b.shape, name
            torch.testing.assert_close(a, b, atol=1e-5, rtol=1e-5, msg=name)


def test_assembly_of_both_keyframes_in_one_pass_equals_one_keyframe_at_a_time(model):
    pair = make_pair(num_views=3, height=16, width=24)
    batch = pair_to_tensors(pair)
    with torch.no_grad():
        static = predict_static(model, batch)
    sky = torch.zeros(2, 3, 16, 24, dtype=torch.bool)
    sky[1, 2, :4] = True
    flows = torch.randn(2, 3, 16, 24, 3)
    both = assemble(static, batch, sky, flows)
    parts = [assemble(static, batch, sky, flows, keyframes=(k,)) for k in (0, 1)]
    assert len(parts[1]) == 3 * 16 * 24 - 4 * 24
    for name in ("means", "quats", "log_scales", "opacity_logits", "sh", "flows", "keyframes", "cameras"):
        assert torch.equal(getattr(both, name), torch.cat([getattr(p, name) for p in parts])), name
    assert torch.equal(parts[1].keyframes.unique(), torch.tensor([1]))
    assert torch.equal(parts[1].cameras.unique(), torch.tensor([0, 1, 2]))


def test_networks_run_at_the_training_size_and_outputs_come_back_full_size():
    """A model trained at 32x48 reconstructs a 64x96 pair: networks at 32x48, outputs at 64x96."""
    import dataclasses

    torch.manual_seed(0)
    small_model = DrivingSceneModel(dataclasses.replace(SMALL, input_size=(32, 48))).eval()
    pair = make_pair(num_views=2, height=64, width=96)
    batch = pair_to_tensors(pair)
    with torch.no_grad():
        static = predict_static(small_model, batch)
        flow = predict_flow(small_model, batch, static.depth)
    assert static.depth.shape == (2, 2, 64, 96) and static.params.sh.shape[:3] == (4, 64, 96)
    assert static.depth_output.depth.shape[-2:] == (32, 48)
    assert flow.residual.shape == (2, 2, 64, 96, 2)
    # Depth is a property of the scene, not of the pixel grid: the 64x96 depth, shrunk, matches
    # the depth the network predicts on the 32x48 images (focal scaling keeps metres metres).
    shrunk = torch.nn.functional.interpolate(1 / static.depth.flatten(0, 1)[:, None], size=(32, 48), mode="area")[:, 0]
    torch.testing.assert_close(1 / shrunk, static.depth_output.depth.float(), rtol=0.05, atol=0.0)


def test_rigid_flow_is_bounded_and_zero_for_points_that_pass_behind_the_camera():
    from drivingscene.geometry.flow import rigid_flow
    from drivingscene.models.pipeline import NEAR_Z

    # The ego drives 8 m forward; a point 3 m ahead of the front camera ends up behind it.
    pair = make_pair(height=12, width=16)
    batch = pair_to_tensors(pair)
    depth = torch.full((2, batch.num_views, 12, 16), 3.0)
    c2l = batch.cam_to_local.clone()
    forward = torch.eye(4).repeat(batch.num_views, 1, 1)
    forward[:, 0, 3] = 8.0
    batch = replace(batch, cam_to_local=torch.stack([c2l[0], forward @ c2l[0]]))
    flow = rigid_flows(depth, batch)
    dest = flow + pixel_grid(12, 16)
    assert torch.isfinite(flow).all()
    assert dest[..., 0].min() >= -16 and dest[..., 0].max() <= 31
    assert dest[..., 1].min() >= -12 and dest[..., 1].max() <= 23
    # No static-world flow behind the camera: 0 there (the point moves with the ego, or is gone).
    _, z = rigid_flow(depth[0], batch.intrinsics, batch.cam_to_local[0], batch.cam_to_local[1])
    behind = z < NEAR_Z
    assert behind.any() and (~behind).any()
    assert (flow[0][behind] == 0).all() and (flow[0][~behind].norm(dim=-1) > 1).all()
    # Points that stay in front keep their exact flow: bounding only touches far destinations.
    near = rigid_flows(torch.full_like(depth, 200.0), batch)
    assert near.abs().max() < 8


def test_sparse_lift_matches_the_dense_definition_and_passes_gradients():
    from drivingscene.geometry.flow import forward_backward_consistency
    from drivingscene.geometry.scene_flow import scene_flow_from_optical_flow

    g = torch.Generator().manual_seed(3)
    pair = make_pair(num_views=3, height=20, width=28)
    batch = pair_to_tensors(pair)
    depth = 3.0 + 20.0 * torch.rand(2, 3, 20, 28, generator=g)
    rigid = torch.randn(2, 3, 20, 28, 2, generator=g)
    residual = 3.0 * torch.randn(2, 3, 20, 28, 2, generator=g) * (torch.rand(2, 3, 20, 28, 1, generator=g) < 0.4)
    residual[1] = -residual[0]  # some forward/backward-consistent motion
    total = (rigid + residual).requires_grad_(True)
    sky = torch.rand(2, 3, 20, 28, generator=g) < 0.1
    config = LiftConfig(dynamic_threshold_px=1.0)
    flows, masks = lift_scene_flow(depth, total, residual, sky, batch, config)
    c2l = batch.cam_to_local
    for k in (0, 1):
        sf, valid = scene_flow_from_optical_flow(depth[k], depth[1 - k], total[k].detach(), batch.intrinsics, c2l[k], c2l[1 - k])
        consistent = forward_backward_consistency(total[k].detach(), total[1 - k].detach())
        dynamic = valid & consistent & (residual[k].norm(dim=-1) > 1.0) & ~sky[k]
        assert 0 < dynamic.sum() < dynamic.numel()
        assert torch.equal(masks[k], dynamic)
        torch.testing.assert_close(
            flows[k].detach(), torch.where(dynamic[..., None], sf, torch.zeros_like(sf)), atol=1e-4, rtol=1e-5
        )
    flows.square().sum().backward()
    assert total.grad is not None and total.grad.abs().sum() > 0
    # Many candidates: the dense path gives the same flows and masks.
    import drivingscene.models.lift as pipeline

    many = residual + 3.0 * (torch.rand(2, 3, 20, 28, 1, generator=g) < 0.5)
    previous = pipeline.DENSE_LIFT_SHARE
    try:
        pipeline.DENSE_LIFT_SHARE = 1.0  # never dense
        sparse = lift_scene_flow(depth, rigid + many, many, sky, batch, config)
        pipeline.DENSE_LIFT_SHARE = 0.0  # always dense
        dense = lift_scene_flow(depth, rigid + many, many, sky, batch, config)
    finally:
        pipeline.DENSE_LIFT_SHARE = previous
    assert torch.equal(dense[1], sparse[1]) and 0 < sparse[1].sum() < sparse[1].numel()
    torch.testing.assert_close(dense[0], sparse[0], atol=1e-5, rtol=1e-5)
    # Pixels in any order (one matrix per pixel) give what sorted ones (one product per camera) give.
    from drivingscene.geometry.scene_flow import scene_flow_at_pixels

    index, row, col = masks[0].nonzero(as_tuple=True)
    pixels = torch.stack([col, row], -1)
    order = torch.randperm(len(index), generator=g)
    args = (depth[0], depth[1], total[0].detach(), batch.intrinsics, c2l[0], c2l[1])
    sorted_sf, _ = scene_flow_at_pixels(*args, index, pixels)
    shuffled_sf, _ = scene_flow_at_pixels(*args, index[order], pixels[order])
    torch.testing.assert_close(shuffled_sf, sorted_sf[order], atol=1e-5, rtol=1e-5)
    # The threshold is in pixels of the networks' input: networks at half this width -> 2 px here.
    _, half = lift_scene_flow(depth, total.detach(), residual, sky, batch, config, net_width=14)
    _, two_px = lift_scene_flow(depth, total.detach(), residual, sky, batch, LiftConfig(dynamic_threshold_px=2.0))
    assert torch.equal(half, two_px) and half.sum() < masks.sum()


def test_photometric_check_keeps_only_residuals_that_explain_the_images():
    from drivingscene.models.lift import total_flow_matches_better

    g = torch.Generator().manual_seed(5)
    target = torch.rand(1, 24, 32, 3, generator=g)
    source = target.roll(shifts=4, dims=2)  # the content moved 4 px to the right
    rigid = torch.zeros(1, 24, 32, 2)
    right, wrong = rigid.clone(), rigid.clone()
    right[..., 0], wrong[..., 0] = 4.0, 7.0
    row, col = torch.meshgrid(torch.arange(2, 22), torch.arange(2, 23), indexing="ij")  # away from the wrap
    pixels = torch.stack([col.flatten(), row.flatten()], -1)
    index = torch.zeros(len(pixels), dtype=torch.long)
    assert total_flow_matches_better(target, source, right, rigid, index, pixels).all()
    # A residual on top of a rigid flow that already explains the pixel is not trusted.
    assert not total_flow_matches_better(target, source, wrong, right, index, pixels).any()
    assert not total_flow_matches_better(target, target, right, rigid, index, pixels).any()  # nothing moved
    # A total flow that leaves the image is never trusted; a rigid one that leaves it always loses.
    edge = torch.tensor([[30, 5]])
    assert not total_flow_matches_better(target, source, right, rigid, index[:1], edge).any()
    assert total_flow_matches_better(target, source, rigid, right, index[:1], edge).all()

    # In the lift, the check only removes candidates, and only with the rigid flow given.
    pair = make_pair(num_views=3, height=20, width=28)
    batch = pair_to_tensors(pair)
    depth = 3.0 + 20.0 * torch.rand(2, 3, 20, 28, generator=g)
    rigid = torch.randn(2, 3, 20, 28, 2, generator=g)
    residual = 3.0 * torch.randn(2, 3, 20, 28, 2, generator=g)
    residual[1] = -residual[0]
    sky = torch.zeros(2, 3, 20, 28, dtype=torch.bool)
    config = LiftConfig(dynamic_threshold_px=1.0, photometric_check=True)
    _, unchecked = lift_scene_flow(depth, rigid + residual, residual, sky, batch, config)
    _, checked = lift_scene_flow(depth, rigid + residual, residual, sky, batch, config, rigid=rigid)
    off = replace(config, photometric_check=False)
    _, switched_off = lift_scene_flow(depth, rigid + residual, residual, sky, batch, off, rigid=rigid)
    assert torch.equal(switched_off, unchecked)
    assert checked.sum() < unchecked.sum() and not (checked & ~unchecked).any()


def test_pixels_without_rigid_flow_move_with_the_ego_when_consistent():
    """Behind the other camera the rigid flow is 0; a zero residual there means the surface kept its
    place in the image: it moved with the ego, and the lift moves its Gaussian by the ego motion."""
    batch = pair_to_tensors(make_pair(num_views=2, height=12, width=16))
    depth = torch.full((2, 2, 12, 16), 4.0)
    total = torch.zeros(2, 2, 12, 16, 2)
    sky = torch.zeros(2, 2, 12, 16, dtype=torch.bool)
    behind = torch.zeros_like(sky)
    behind[:, 0, 3:7, 4:9] = True
    flows, masks = lift_scene_flow(depth, total, total, sky, batch, LiftConfig(), behind=behind)
    assert torch.equal(masks, behind)
    # The same camera-frame point at both keyframes: it moved exactly as the camera did.
    c2l, k_inv = batch.cam_to_local.double(), torch.linalg.inv(batch.intrinsics[0].double())
    ray = k_inv @ torch.tensor([5.0, 4.0, 1.0], dtype=torch.float64)  # pixel (u=5, v=4)
    point = torch.cat([4.0 * ray / ray[2], torch.ones(1, dtype=torch.float64)])
    moved = (c2l[1, 0] @ point - c2l[0, 0] @ point)[:3]
    assert moved.norm() > 0.1
    torch.testing.assert_close(flows[0, 0, 4, 5].double(), moved, atol=1e-4, rtol=1e-4)
    _, off = lift_scene_flow(depth, total, total, sky, batch, LiftConfig(behind_candidates=False), behind=behind)
    assert not off.any()


def test_search_keeps_the_flow_that_explains_the_images_at_full_size():
    """Both keyframes show the same image although the rigid flow says 3 px: the content kept pace
    with the ego, and the search (run at half size, applied at full size) finds the zero flow."""
    from drivingscene.models.lift import MotionSearchConfig, search_motion
    from drivingscene.models.pipeline import FlowPrediction

    batch = pair_to_tensors(make_pair(num_views=2, height=24, width=32))
    g = torch.Generator().manual_seed(3)
    texture = F.avg_pool2d(torch.rand(2, 3, 24, 32, generator=g), 3, stride=1, padding=1)
    batch = replace(batch, images=torch.stack([texture, texture]))
    rigid = torch.zeros(2, 2, 24, 32, 2)
    rigid[..., 0] = 3.0
    flow = FlowPrediction(rigid=rigid, residuals=[torch.zeros_like(rigid)], warped_sources=torch.zeros(2, 2, 3, 24, 32))
    searched = search_motion(flow, batch, MotionSearchConfig(), net_size=(12, 16))
    assert searched.searched.shape == rigid.shape and flow.searched is None
    assert searched.total[..., 4:-4, 4:-4, :].abs().max() < 0.05  # s = 0: no motion in the image
    torch.testing.assert_close(searched.residual, searched.total - rigid)
    # Without R's proposal (diagnostic) the choice is among multiples of the rigid flow only.
    alone = search_motion(flow, batch, MotionSearchConfig(use_network=False), net_size=(12, 16)).total
    ratios = alone[..., 0] / 3.0
    grid = MotionSearchConfig().scales()
    assert (ratios[..., None] - grid).abs().amin(-1).max() < 1e-5
    with pytest.raises(ValueError, match="window"):
        MotionSearchConfig(window=2)
    with pytest.raises(ValueError, match="proposal_level"):
        MotionSearchConfig(proposal_level=-1)


def test_compiled_dense_lift_matches_the_torch_path(compiled_kernels, monkeypatch):
    """Nearly every pixel a candidate (the dense branch): smooth flows that the backward flow undoes
    with noise added, so that some pixels fail the forward/backward check, and some depths 0 (invalid)."""
    from drivingscene import kernels

    batch = pair_to_tensors(make_pair(num_views=2, height=24, width=32))
    g = torch.Generator().manual_seed(7)
    depth = 2 + 20 * torch.rand(2, 2, 24, 32, generator=g)
    depth[torch.rand(depth.shape, generator=g) < 0.05] = 0.0
    shift = torch.tensor([3.0, -1.5])
    noise = torch.randn(2, 2, 24, 32, 2, generator=g) * (torch.rand(2, 2, 24, 32, 1, generator=g) < 0.2)
    total = torch.stack([shift.expand(2, 24, 32, 2), -shift.expand(2, 24, 32, 2)]) + 2 * noise
    sky = torch.zeros(2, 2, 24, 32, dtype=torch.bool)
    sky[:, :, :3] = True
    chosen = []

    def spy(op, *args):
        compiled = available(op, *args)
        chosen.append((op.__name__, compiled))
        return compiled

    available = kernels.available
    monkeypatch.setattr(kernels, "available", spy)
    fast, fast_mask = lift_scene_flow(depth, total, total, sky, batch, LiftConfig())
    assert chosen == [("lift_dense", True)] * 2
    monkeypatch.setattr(kernels, "available", lambda op, *args: op is not kernels.lift_dense and available(op, *args))
    slow, slow_mask = lift_scene_flow(depth, total, total, sky, batch, LiftConfig())
    assert 0.2 < slow_mask.float().mean() < 0.9  # both outcomes occur
    assert (fast_mask == slow_mask).float().mean() > 0.999
    both = fast_mask & slow_mask
    torch.testing.assert_close(fast[both], slow[both], atol=1e-4, rtol=1e-4)
    assert not fast[~fast_mask].any()  # static pixels do not move


def test_compiled_epipolar_geometry_matches_the_torch_path(compiled_kernels):
    """`epipolar_geometry`'s compiled op and torch path agree: flows around the rigid flow of a
    turning ego, some pixels pushed off the image or behind the camera."""
    from drivingscene.models.lift import epipolar_geometry

    pair = make_pair(num_views=3, height=24, width=32)
    yaw = math.radians(8.0)
    pair.ego_to_world[1, :2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
    batch = pair_to_tensors(pair)
    g = torch.Generator().manual_seed(11)
    depth = 2.0 + 40.0 * torch.rand(2, 3, 24, 32, generator=g)
    rigid, _ = rigid_flows_and_behind(depth, batch)
    flow = rigid + 3.0 * torch.randn(rigid.shape, generator=g)
    c2l = batch.cam_to_local.float()
    for k in (0, 1):
        rel = torch.linalg.inv(c2l[1 - k]) @ c2l[k]
        fast = epipolar_geometry(flow[k], batch.intrinsics.float(), rel, backend="cpp")
        slow = epipolar_geometry(flow[k], batch.intrinsics.float(), rel, backend="torch")
        assert 0.3 < slow[3].float().mean() < 1.0  # valid and invalid pixels both occur
        assert (fast[3] == slow[3]).float().mean() > 0.999
        both = fast[3] & slow[3]
        for a, b in zip(fast[:3], slow[:3]):
            torch.testing.assert_close(a[both], b[both], rtol=1e-3, atol=1e-3)


@pytest.mark.parametrize("scale", [1.0, 1.8])
def test_texture_along_the_line_is_what_kornia_computes(scale):
    """`texture_along` (central differences, OpenCV's box filter) against kornia's gradient and box blur."""
    from kornia.filters import box_blur, spatial_gradient

    from drivingscene.geometry.flow_search import luma
    from drivingscene.models.lift import texture_along

    g = torch.Generator().manual_seed(2)
    images, direction = torch.rand(3, 3, 30, 40, generator=g), torch.randn(3, 30, 40, 2, generator=g)
    grad = spatial_gradient(luma(images), mode="diff", order=1)[:, 0] * scale
    along = (grad * F.normalize(direction, dim=-1).permute(0, 3, 1, 2)).sum(1, keepdim=True).abs()
    size = max(1, int(round(5 * scale))) | 1
    expected = box_blur(along, (size, size), border_type="replicate")[:, 0]
    torch.testing.assert_close(texture_along(images, direction, scale), expected, rtol=1e-5, atol=1e-6)


def test_small_dynamic_regions_are_dropped():
    from drivingscene.models.lift import drop_small_regions

    mask = torch.zeros(2, 1, 10, 12, dtype=torch.bool)
    mask[0, 0, 1:4, 1:4] = True  # 9 pixels
    mask[0, 0, 6, 8] = True  # 1 pixel
    mask[1, 0, 5:7, 2:4] = True  # 4 pixels
    kept = drop_small_regions(mask, 4)
    assert kept[0, 0, 1:4, 1:4].all() and not kept[0, 0, 6, 8] and kept[1].sum() == 4
    assert drop_small_regions(mask, 10).sum() == 0
    assert torch.equal(drop_small_regions(mask, 0), mask)


def test_parallax_explains_a_wrong_depth_but_not_motion_off_the_epipolar_line():
    """`explain_by_parallax`: a static world seen with half its depth (the total flow the true
    rigid flow) is explained at its true depth, also with the ego turning; flow 4 px off the
    epipolar line, or a point that would have to lie behind the camera, is not explained; without
    enough parallax or texture along the line a pixel is explained but keeps its depth."""
    from drivingscene.models.lift import explain_by_parallax
    from drivingscene.models.pipeline import FlowPrediction, with_depth

    g = torch.Generator().manual_seed(5)
    pair = make_pair(num_views=3, height=24, width=32)
    yaw = math.radians(6.0)
    pair.ego_to_world[1, :2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
    batch = pair_to_tensors(pair)
    true_depth = 4.0 + 30.0 * torch.rand(2, 3, 24, 32, generator=g)
    wrong = 0.5 * true_depth
    true_rigid, behind = rigid_flows_and_behind(true_depth, batch)
    rigid, behind_wrong = rigid_flows_and_behind(wrong, batch)
    behind = behind | behind_wrong
    config = LiftConfig(epipolar_static=True, epipolar_px=1.0, epipolar_near=1.0, epipolar_far=80.0, epipolar_min_parallax=0.0)
    flow = FlowPrediction(rigid=rigid, residuals=[true_rigid - rigid], warped_sources=torch.zeros(1), behind=behind)
    tested = ((true_rigid - rigid).norm(dim=-1) > 1.0) & ~behind  # what the lift would call moving
    depth, out, explained = explain_by_parallax(wrong, flow, tested, batch, config)
    end = pixel_grid(24, 32) + true_rigid
    inside = (end[..., 0] >= 0) & (end[..., 0] <= 31) & (end[..., 1] >= 0) & (end[..., 1] <= 23)
    candidate = tested & inside
    assert candidate.float().mean() > 0.2
    assert explained[candidate].float().mean() > 0.95 and not explained[~candidate].any()
    torch.testing.assert_close(depth[explained], true_depth[explained], rtol=2e-3, atol=1e-3)
    assert torch.equal(depth[~explained], wrong[~explained])
    assert torch.equal(out.total, flow.total) and (out.residual[explained] == 0).all()
    # Moved 4 px across the epipolar line (the line's direction: from the far to the near point).
    far_rigid, _ = rigid_flows_and_behind(2.0 * true_depth, batch)
    along = F.normalize(true_rigid - far_rigid, dim=-1)
    across = torch.stack([-along[..., 1], along[..., 0]], -1)
    moved = replace(flow, residuals=[true_rigid + 4.0 * across - rigid])
    assert not explain_by_parallax(wrong, moved, tested, batch, config)[2][candidate & (along.norm(dim=-1) > 0.5)].any()
    # Pulling away faster than the ego: past the point at infinity on the line (the flow of a
    # point infinitely far, the rotation's alone), which no static depth explains.
    infinity, _ = rigid_flows_and_behind(torch.full_like(true_depth, 1e5), batch)
    beyond = infinity - 0.5 * (true_rigid - infinity)
    away = replace(flow, residuals=[beyond - rigid])
    end = pixel_grid(24, 32) + beyond
    inside = (end[..., 0] >= 0) & (end[..., 0] <= 31) & (end[..., 1] >= 0) & (end[..., 1] <= 23)
    backwards = ((beyond - rigid).norm(dim=-1) > 1.0) & ~behind & ((true_rigid - infinity).norm(dim=-1) > 2.0) & inside
    assert backwards.any() and not explain_by_parallax(wrong, away, backwards, batch, config)[2].any()
    # Too little parallax (or texture along the line) to tell the depth: static at the network's depth.
    for strict in (dict(epipolar_min_parallax=1e3), dict(epipolar_min_texture=1e3)):
        kept, kept_flow, same = explain_by_parallax(wrong, flow, tested, batch, replace(config, **strict))
        assert torch.equal(same, explained) and torch.equal(kept, wrong) and torch.equal(kept_flow.rigid, rigid)
    # Pixels marked fixed (matched at inference) stay static at their own depth.
    fixed = torch.zeros_like(tested)
    fixed[0] = True
    held, _, same = explain_by_parallax(wrong, flow, tested, batch, config, fixed=fixed)
    assert torch.equal(same, explained) and torch.equal(held[0], wrong[0]) and torch.equal(held[1], depth[1])
    # The Gaussians follow the new depth: scales by the same ratio.
    from drivingscene.models.gaussian_head import PixelGaussians
    from drivingscene.models.pipeline import StaticPrediction

    params = PixelGaussians(
        log_scales=torch.zeros(6, 24, 32, 3),
        quats=torch.zeros(6, 24, 32, 4),
        opacity_logits=torch.zeros(6, 24, 32),
        sh=torch.zeros(6, 24, 32, 1, 3),
    )
    static = with_depth(StaticPrediction(depth=wrong, depth_output=None, params=params), depth)
    torch.testing.assert_close(static.params.log_scales[..., 0], (depth / wrong).log().flatten(0, 1))
