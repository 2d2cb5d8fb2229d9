"""Losses with a ``valid_mask``: pixels that do not see the world (ego body, hood) count in no loss.

Without a mask every loss is its unmasked formula exactly; with one, values inside the mask do not
change the loss (images perturbed only there give the identical loss) and receive no gradient.
"""

from __future__ import annotations

import kornia
import pytest
import torch

from drivingscene.geometry.flow import backward_warp
from drivingscene.models.losses import blank_masked, consistency_loss, render_loss, sampled_from, smoothness_loss

H, W = 36, 40


def _rand(*shape, seed=0):
    return torch.rand(*shape, generator=torch.Generator().manual_seed(seed))


def _hood(batch: int = 2) -> torch.Tensor:
    """``[B, H, W]`` bool: False on a hood at the bottom and a mount at the left edge."""
    mask = torch.ones(batch, H, W, dtype=torch.bool)
    mask[:, 26:, 6:30] = False
    mask[:, :10, :3] = False
    return mask


def _perturbed(x: torch.Tensor, mask: torch.Tensor, seed: int = 9) -> torch.Tensor:
    """``x`` ``[B, C, H, W]`` or ``[B, H, W, C]`` with new values where ``mask`` ``[B, H, W]`` is False."""
    other = _rand(*x.shape, seed=seed) * 5 - 2
    keep = mask[:, None] if x.shape[1] != mask.shape[1] else mask[..., None]
    return torch.where(keep, x, other)


@pytest.fixture(scope="module")
def perceptual():
    from drivingscene.eval.lpips import load_perceptual

    return load_perceptual("stlpips", "alex")


def test_sampled_from_is_exact_about_bilinear_neighbours():
    mask = torch.ones(1, 6, 8, dtype=torch.bool)
    mask[0, :, 5] = False
    flow = torch.zeros(1, 6, 8, 2)
    ok = sampled_from(mask, flow)
    assert torch.equal(ok, mask)  # zero flow: each pixel reads itself
    flow[..., 0] = 0.5  # half a pixel right: columns 4 and 5 read column 5
    ok = sampled_from(mask, flow)
    assert not ok[0, :, 4].any() and not ok[0, :, 5].any() and ok[0, :, [3, 6]].all()


def test_blank_masked_equalises_and_hides_masked_pixels():
    pred, target, mask = _rand(2, 3, H, W, seed=1), _rand(2, 3, H, W, seed=2), _hood()
    seen = mask.clone()
    seen[:, 20] = False  # a row of pred that must not be compared although the target sees the world
    p, t = blank_masked(pred, target, seen, mask)
    assert (t[:, :, ~mask[0]] == 0).all() and (p[:, :, ~mask[0]] == 0).all()
    assert torch.equal(p[:, :, 20], t[:, :, 20]) and torch.equal(t[:, :, 20], target[:, :, 20])
    assert torch.equal(p[:, :, 21], pred[:, :, 21])
    p2, t2 = blank_masked(_perturbed(pred, seen), _perturbed(target, mask, seed=4), seen, mask)
    assert torch.equal(p, p2) and torch.equal(t, t2)


def test_without_a_mask_the_losses_are_the_unmasked_formulas(perceptual):
    disp, image = _rand(2, 1, 18, 20, seed=1), _rand(2, 3, H, W, seed=2)
    small = torch.nn.functional.interpolate(image, size=(18, 20), mode="area")
    old_smooth = kornia.losses.inverse_depth_smoothness_loss(disp / disp.mean(dim=(2, 3), keepdim=True), small)
    assert torch.equal(smoothness_loss(disp, image), old_smooth)
    pred, target = _rand(2, 3, H, W, seed=3), _rand(2, 3, H, W, seed=4)
    old_render = (pred - target).square().mean() + 0.05 * perceptual(pred, target).mean()
    assert torch.equal(render_loss(pred, target, perceptual), old_render)
    fw, bw = _rand(2, H, W, 2, seed=5) * 4 - 2, _rand(2, H, W, 2, seed=6) * 4 - 2
    bw_at_fw, inside = backward_warp(bw.permute(0, 3, 1, 2), fw)
    old_consist = ((fw + bw_at_fw.permute(0, 2, 3, 1)).abs().sum(-1) * inside).sum() / inside.sum().clamp(min=1)
    assert torch.equal(consistency_loss(fw, bw), old_consist)


def test_an_all_true_mask_changes_nothing_but_rounding(perceptual):
    ones = torch.ones(2, H, W, dtype=torch.bool)
    disp, image = _rand(2, 1, 18, 20, seed=1), _rand(2, 3, H, W, seed=2)
    torch.testing.assert_close(smoothness_loss(disp, image, ones), smoothness_loss(disp, image))
    pred, target = _rand(2, 3, H, W, seed=3), _rand(2, 3, H, W, seed=4)
    torch.testing.assert_close(render_loss(pred, target, perceptual, mask=ones), render_loss(pred, target, perceptual))
    fw, bw = _rand(2, H, W, 2, seed=5) * 4 - 2, _rand(2, H, W, 2, seed=6) * 4 - 2
    torch.testing.assert_close(consistency_loss(fw, bw, ones, ones), consistency_loss(fw, bw))


@pytest.mark.parametrize("size", [(H, W), (18, 20), (9, 10)])
def test_smoothness_ignores_masked_pixels(size):
    mask = _hood()
    disp = (_rand(2, 1, *size, seed=1) + 0.5).requires_grad_(True)
    image = _rand(2, 3, H, W, seed=2)
    loss = smoothness_loss(disp, image, mask)
    off = torch.nn.functional.interpolate((~mask)[:, None].float(), size=size, mode="area") > 0  # [2, 1, h, w]
    other_disp = torch.where(off, _rand(2, 1, *size, seed=3) * 100, disp.detach())
    assert torch.equal(smoothness_loss(other_disp, _perturbed(image, mask), mask), loss.detach())
    loss.backward()
    assert disp.grad[off].abs().max() == 0 and disp.grad[~off].abs().max() > 0
    # a disparity step only at the masked pixels' edges: no loss with the mask, some without
    step = torch.where(off, torch.full_like(disp.detach(), 10.0), torch.ones_like(disp.detach()))
    assert smoothness_loss(step, image, mask) == 0 < smoothness_loss(step, image)


def test_render_loss_ignores_masked_pixels(perceptual):
    mask = _hood()
    pred = _rand(2, 3, H, W, seed=1).requires_grad_(True)
    target = _rand(2, 3, H, W, seed=2)
    loss = render_loss(pred, target, perceptual, mask=mask)
    assert torch.equal(
        render_loss(_perturbed(pred.detach(), mask), _perturbed(target, mask), perceptual, mask=mask), loss.detach()
    )
    loss.backward()
    assert pred.grad[:, :, ~mask[0]].abs().max() == 0 and pred.grad[:, :, mask[0]].abs().max() > 0
    no_lpips = render_loss(pred.detach(), target, None, mask=mask)
    torch.testing.assert_close(no_lpips, (pred.detach() - target).square().mean(1)[mask].mean())


def test_consistency_ignores_masked_pixels_and_samples_landing_on_them():
    mask = _hood()
    fw = (_rand(2, H, W, 2, seed=5) * 4 - 2).requires_grad_(True)
    bw = (_rand(2, H, W, 2, seed=6) * 4 - 2).requires_grad_(True)
    loss = consistency_loss(fw, bw, mask, mask)
    same = consistency_loss(_perturbed(fw.detach(), mask), _perturbed(bw.detach(), mask), mask, mask)
    assert torch.equal(same, loss.detach())
    loss.backward()
    for flow in (fw, bw):
        assert flow.grad[~mask].abs().max() == 0 and flow.grad[mask].abs().max() > 0


# -- the training step: where PairTensors meet the losses ------------------------------------------


@pytest.fixture(scope="module")
def step_setup(perceptual):
    """A TrainStep with a tiny model, a pair of 3 cameras at 32 x 48 with a hood mask, and the
    pair's static prediction."""
    from dataclasses import replace

    from drivingscene.data.tensors import pair_to_tensors
    from drivingscene.models.model import DrivingSceneModel
    from drivingscene.models.pipeline import predict_static
    from drivingscene.train.config import TrainConfig
    from drivingscene.train.stages import TrainStep
    from tests.factories import make_pair
    from tests.train.test_trainer import TINY_MODEL

    torch.manual_seed(0)
    step = TrainStep(DrivingSceneModel(TINY_MODEL), TrainConfig(stage="joint", model=TINY_MODEL, amp=False), perceptual)
    batch = pair_to_tensors(make_pair(3, 32, 48, seed=1))
    mask = torch.ones(3, 32, 48, dtype=torch.bool)
    mask[:, 22:, 8:40] = False
    mask[0, :, :4] = False
    masked = replace(batch, valid_mask=mask)
    with torch.no_grad():
        static = predict_static(step.model, batch)
    return step, batch, masked, static


def _perturb_batch(batch):
    """``batch`` with its keyframe and intermediate images changed only off its ``valid_mask``."""
    from dataclasses import replace

    keep = batch.valid_mask[None, :, None]  # [1, V, 1, H, W]
    return replace(
        batch,
        images=torch.where(keep, batch.images, _rand(*batch.images.shape, seed=11)),
        eval_images=torch.where(keep, batch.eval_images, _rand(*batch.eval_images.shape, seed=12)),
    )


def _old_location_loss(depth, batch, targets):
    """L_loc as it was before masks, for the bit-identity check."""
    from drivingscene.geometry.flow import rigid_flow
    from drivingscene.models.losses import reprojection_loss
    from drivingscene.train.stages import _source_sets

    c2l, k = batch.cam_to_local.flatten(0, 1), batch.intrinsics.repeat(2, 1, 1)
    warped, valid, identity = [], [], []
    for i, (src_kf, src_cam) in enumerate(_source_sets(batch)):
        src = src_kf * batch.num_views + src_cam
        flow, z = rigid_flow(depth.flatten(0, 1).float(), k, c2l, c2l[src], dst_intrinsics=k[src])
        image, inside = backward_warp(targets[src], flow)
        warped.append(image)
        valid.append(inside & (z > 0.1))
        if i == 0:
            identity.append(targets[src])
    return reprojection_loss(targets, warped, valid, identity)[0]


def _location_loss(step, depth, batch):
    torch.manual_seed(0)  # the auto-mask's tie-breaking noise
    return step.location_loss(depth, batch, batch.images.flatten(0, 1))


def test_location_loss_without_a_mask_is_as_before(step_setup):
    step, batch, _, static = step_setup
    torch.manual_seed(0)
    old = _old_location_loss(static.depth, batch, batch.images.flatten(0, 1))
    assert torch.equal(_location_loss(step, static.depth, batch), old)


def test_location_loss_ignores_masked_targets_and_sources(step_setup):
    step, _, masked, static = step_setup
    depth = static.depth.clone().requires_grad_(True)
    loss = _location_loss(step, depth, masked)
    assert torch.equal(_location_loss(step, depth.detach(), _perturb_batch(masked)), loss.detach())
    loss.backward()
    off = ~masked.valid_mask.expand(2, -1, -1, -1)
    assert depth.grad[off].abs().max() == 0 and depth.grad[~off].abs().max() > 0


def test_warp_loss_ignores_masked_pixels(step_setup, perceptual):
    from drivingscene.models.losses import warp_loss
    from drivingscene.train.stages import _masked_warp, _world

    _, _, masked, _ = step_setup
    world = _world(masked)  # [2V, H, W]
    flow = (_rand(6, 32, 48, 2, seed=3) * 6 - 3).requires_grad_(True)

    def loss_of(batch, flow):
        sources, targets = batch.images.flip(0).flatten(0, 1), batch.images.flatten(0, 1)
        warped, compared, valid = _masked_warp(sources, targets, flow, world, world)
        return warp_loss(warped, compared, valid, perceptual)

    loss = loss_of(masked, flow)
    assert torch.equal(loss_of(_perturb_batch(masked), flow.detach()), loss.detach())
    loss.backward()
    assert flow.grad[~world].abs().max() == 0 and flow.grad[world].abs().max() > 0


@pytest.mark.parametrize("index", [0, 1])  # render the intermediate frame, then a keyframe
def test_render_term_ignores_masked_pixels(step_setup, index):
    step, _, masked, static = step_setup
    loss = step.render_term(static, masked, index, scene_flow=None)
    assert torch.equal(step.render_term(static, _perturb_batch(masked), index, scene_flow=None), loss)


@pytest.mark.parametrize("stage", ["static", "dynamic", "joint"])
def test_training_step_with_an_all_true_mask_is_the_step_without_one(step_setup, stage):
    from dataclasses import replace

    from drivingscene.train.stages import TrainStep

    shared, batch, masked, _ = step_setup
    step = TrainStep(shared.model, replace(shared.config, stage=stage), shared.perceptual)

    def loss_of(b):
        torch.manual_seed(0)
        with torch.no_grad():
            return step(b, 0)[0]

    everything = replace(batch, valid_mask=torch.ones_like(masked.valid_mask))
    torch.testing.assert_close(loss_of(everything), loss_of(batch), rtol=1e-5, atol=1e-7)
    assert torch.isfinite(loss_of(masked))
