"""Each loss against its definition on constructed inputs."""

from __future__ import annotations

import math

import torch

from drivingscene.models.losses import (
    consistency_loss,
    photometric_error,
    render_loss,
    reprojection_loss,
    search_distillation_loss,
    smoothness_loss,
    supervised_depth_loss,
    supervised_flow_loss,
    warp_loss,
)


def _image(seed=0, h=16, w=20):
    return torch.rand(1, 3, h, w, generator=torch.Generator().manual_seed(seed))


def test_photometric_error_is_zero_for_identical_and_grows_with_difference():
    a = _image()
    assert photometric_error(a, a).abs().max() < 1e-5
    small = photometric_error((a + 0.05).clamp(0, 1), a).mean()
    large = photometric_error((a + 0.3).clamp(0, 1), a).mean()
    assert 0 < small < large


def test_reprojection_takes_the_best_valid_source_per_pixel():
    target = _image(0)
    good, bad = target.clone(), _image(1)
    ones = torch.ones(1, 16, 20, dtype=torch.bool)
    loss, used = reprojection_loss(target, [bad, good], [ones, ones])
    assert loss < 1e-4 and used.all()
    # The good source is invalid on the left half: those pixels must use the bad source.
    left = ones.clone()
    left[..., :10] = False
    loss_left, _ = reprojection_loss(target, [bad, good], [ones, left])
    expected = photometric_error(bad, target)[..., :10].sum() / (16 * 20)
    torch.testing.assert_close(loss_left, expected, rtol=1e-4, atol=1e-6)


def test_automask_drops_pixels_an_unwarped_source_explains():
    target = _image(0)
    warped = (target + 0.2).clamp(0, 1)
    ones = torch.ones(1, 16, 20, dtype=torch.bool)
    _, used = reprojection_loss(target, [warped], [ones], identity=[target.clone()])
    assert not used.any()  # the identity matches perfectly everywhere: nothing to learn from
    _, used = reprojection_loss(target, [warped], [ones], identity=[_image(3)])
    assert used.float().mean() > 0.5


def test_no_valid_source_gives_zero_loss_not_nan():
    target = _image()
    loss, used = reprojection_loss(target, [_image(1)], [torch.zeros(1, 16, 20, dtype=torch.bool)])
    assert loss == 0 and not used.any()


def test_smoothness_prefers_depth_edges_at_image_edges():
    image = torch.zeros(1, 3, 16, 20)
    image[..., 10:] = 1.0  # an image edge between columns 9 and 10
    flat = torch.ones(1, 1, 16, 20)
    aligned = flat.clone()
    aligned[..., 10:] = 2.0
    misaligned = flat.clone()
    misaligned[..., 5:] = 2.0
    assert smoothness_loss(flat, image) < 1e-6
    assert smoothness_loss(aligned, image) < smoothness_loss(misaligned, image)


def test_render_loss_is_l2_without_perceptual_term():
    a, b = _image(0), _image(1)
    torch.testing.assert_close(render_loss(a, b, None), (a - b).square().mean())


def test_render_loss_adds_weighted_perceptual_term():
    a, b = _image(0), _image(1)
    fake = lambda x, y: torch.full((x.shape[0],), 2.0)  # noqa: E731
    torch.testing.assert_close(render_loss(a, b, fake, 0.05), (a - b).square().mean() + 0.1)


def test_warp_loss_ignores_invalid_pixels():
    target = _image(0)
    warped = target.clone()
    warped[..., :8, :] = 1 - warped[..., :8, :]
    valid = torch.ones(1, 16, 20, dtype=torch.bool)
    valid[:, :8] = False
    # Only the 3x3 SSIM windows straddling the mask border see the invalid rows.
    assert warp_loss(warped, target, valid, None) < 0.01
    assert warp_loss(warped, target, torch.ones_like(valid), None) > 0.1


def test_consistency_loss_zero_for_inverse_flows_and_positive_otherwise():
    fw = torch.zeros(1, 12, 16, 2)
    fw[..., 0] = 2.0
    assert consistency_loss(fw, -fw) < 1e-6
    torch.testing.assert_close(consistency_loss(fw, fw), torch.tensor(4.0))


def test_box_ssim_matches_a_float64_window_loop():
    from drivingscene.models.losses import ssim_box

    x, y = _image(0, 6, 7).double(), _image(1, 6, 7).double()
    got = ssim_box(x, y)
    xp = torch.nn.functional.pad(x, (1, 1, 1, 1), mode="reflect")
    yp = torch.nn.functional.pad(y, (1, 1, 1, 1), mode="reflect")
    c1, c2 = 0.01**2, 0.03**2
    for c in range(3):
        for i in range(6):
            for j in range(7):
                a = xp[0, c, i : i + 3, j : j + 3].flatten()
                b = yp[0, c, i : i + 3, j : j + 3].flatten()
                ma, mb = a.mean(), b.mean()
                va, vb = (a * a).mean() - ma**2, (b * b).mean() - mb**2
                cov = (a * b).mean() - ma * mb
                ref = (2 * ma * mb + c1) * (2 * cov + c2) / ((ma**2 + mb**2 + c1) * (va + vb + c2))
                torch.testing.assert_close(got[0, c, i, j], ref)
    torch.testing.assert_close(ssim_box(x, x), torch.ones_like(x))


def test_supervised_flow_loss_balances_moving_and_static_pixels():
    gt = torch.zeros(1, 4, 10, 2)
    flow = gt.clone()
    dynamic = torch.zeros(1, 4, 10, dtype=torch.bool)
    dynamic[0, 0, 0] = True  # one moving pixel among 40
    valid = torch.ones_like(dynamic)
    assert supervised_flow_loss(flow, gt, dynamic, valid) == 0
    flow[0, 0, 0] = torch.tensor([3.0, 4.0])  # L1 7 px on the moving pixel only
    # half the weight on the moving pixels' mean, whatever their share: 0.5 * 7 / width
    assert torch.isclose(supervised_flow_loss(flow, gt, dynamic, valid), torch.tensor(0.5 * 7 / 10))
    valid[0, 0, 0] = False  # an unusable ground-truth pixel does not count
    assert supervised_flow_loss(flow, gt, dynamic, valid) == 0
    flow.requires_grad_(True)
    supervised_flow_loss(flow + 1, gt, dynamic, valid).backward()
    assert flow.grad[0, 0, 0].abs().sum() == 0 and flow.grad[0, 1, 1].abs().sum() > 0


def test_supervised_depth_loss_is_log_error_balanced_and_skips_unknown_depth():
    gt = torch.full((1, 4, 10), 10.0)
    gt[0, 3] = 0.0  # unknown (sky)
    dynamic = torch.zeros(1, 4, 10, dtype=torch.bool)
    dynamic[0, 0, 0] = True
    assert supervised_depth_loss(gt.clamp(min=1.0), gt, dynamic) == 0  # the unknown row is not scored
    pred = gt.clone()
    pred[0, 0, 0] = 20.0  # the moving pixel twice too far: |log 2| with half the weight
    assert torch.isclose(supervised_depth_loss(pred, gt, dynamic), torch.tensor(0.5 * math.log(2.0)))
    pred.requires_grad_(True)
    supervised_depth_loss(pred * 1.5, gt, dynamic).backward()
    assert pred.grad[0, 3].abs().sum() == 0 and pred.grad[0, 1].abs().sum() > 0


def test_search_distillation_loss_is_masked_l1_over_width_without_gradient_into_the_target():
    flow = torch.zeros(1, 4, 10, 2, requires_grad=True)
    target = torch.zeros(1, 4, 10, 2, requires_grad=True)
    mask = torch.zeros(1, 4, 10, dtype=torch.bool)
    assert search_distillation_loss(flow, target, mask) == 0  # nothing to learn from
    with torch.no_grad():
        target[0, 0, 0] = torch.tensor([3.0, -4.0])
    mask[0, 0, :2] = True  # two target pixels: 7 px and 0 px off
    loss = search_distillation_loss(flow, target, mask)
    assert torch.isclose(loss, torch.tensor(7.0 / 2 / 10))
    loss.backward()
    assert target.grad is None or target.grad.abs().sum() == 0
    assert flow.grad[0, 0, 0].abs().sum() > 0 and flow.grad[0, 1].abs().sum() == 0


def test_search_targets_where_the_search_overrides_r():
    """Both keyframes show the same texture while the rigid flow says 3 px (the content keeps pace
    with the ego): where R followed the rigid flow, the search's zero flow is its target; where R
    already found it, there is nothing to learn."""
    from dataclasses import replace

    import torch.nn.functional as F

    from drivingscene.data.tensors import pair_to_tensors
    from drivingscene.models.pipeline import FlowPrediction
    from drivingscene.train.stages import search_targets
    from tests.factories import make_pair

    batch = pair_to_tensors(make_pair(num_views=2, height=24, width=32))
    texture = F.avg_pool2d(torch.rand(2, 3, 24, 32, generator=torch.Generator().manual_seed(3)), 3, stride=1, padding=1)
    batch = replace(batch, images=torch.stack([texture, texture]))
    rigid = torch.zeros(2, 2, 24, 32, 2)
    rigid[0, ..., 0], rigid[1, ..., 0] = 3.0, -3.0
    follows_rigid = FlowPrediction(rigid=rigid, residuals=[torch.zeros_like(rigid)], warped_sources=torch.zeros(2, 2, 3, 24, 32))
    target, mask = search_targets(follows_rigid, batch)
    assert target.shape == (4, 24, 32, 2) and mask.shape == (4, 24, 32)
    assert mask[:, 6:-6, 6:-6].all()  # interior: the search moved the flow by 3 px, both directions agree
    assert target[:, 6:-6, 6:-6].abs().max() < 0.05
    found = FlowPrediction(rigid=rigid, residuals=[-rigid], warped_sources=torch.zeros(2, 2, 3, 24, 32))
    _, mask = search_targets(found, batch)
    assert not mask.any()
