"""The trivial baselines and masked scoring of in-between frames."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from drivingscene.errors import InputError
from drivingscene.eval.baselines import blend_frames, copy_nearest_frames
from drivingscene.eval.reconstruction import score_frames
from tests.factories import make_pair


def test_copy_nearest_and_blend():
    pair = make_pair(3, 8, 10)  # eval frame at t = 0.5
    images = torch.from_numpy(pair.images).float() / 255
    seconds = np.array([[pair.seconds(0.2), pair.seconds(0.5), pair.seconds(0.8)]])
    pair = replace(pair, eval_camera_timestamps=seconds)
    copy = copy_nearest_frames(pair)
    assert copy.shape == (1, 3, 8, 10, 3)
    assert torch.equal(copy[0, 0], images[0, 0]) and torch.equal(copy[0, 1], images[0, 1])  # a tie goes to keyframe 0
    assert torch.equal(copy[0, 2], images[1, 2])
    blend = blend_frames(pair)
    assert torch.allclose(blend[0, 0], 0.8 * images[0, 0] + 0.2 * images[1, 0])
    assert torch.allclose(blend[0, 2], 0.2 * images[0, 2] + 0.8 * images[1, 2])


def test_baselines_need_eval_frames():
    with pytest.raises(InputError, match="intermediate frames"):
        blend_frames(make_pair(2, 8, 10, with_gt=False))


def test_scores_ignore_masked_pixels():
    pair = make_pair(2, 16, 20)
    target = torch.from_numpy(pair.eval_images).float() / 255
    pred = target.clone()
    pred[:, :, -4:] = 1 - pred[:, :, -4:]  # wrong only in the bottom rows
    mask = np.ones((2, 16, 20), bool)
    mask[:, -4:] = False
    unmasked = score_frames(pred, pair, None)
    masked = score_frames(pred, replace(pair, valid_mask=mask), None)
    assert unmasked["psnr"] < 30 and masked["psnr"] == float("inf")
    # without a mask the scores are those of the metric functions over every pixel
    from drivingscene.eval.metrics import psnr

    flat = psnr(pred.flatten(0, 1).permute(0, 3, 1, 2), target.flatten(0, 1).permute(0, 3, 1, 2))
    assert unmasked["psnr"] == pytest.approx(float(flat.double().mean()))


def _old_score_novel_views(pred, pair, perceptual):
    """score_novel_views before valid_mask, for the bit-identity check."""
    from drivingscene.eval.metrics import lpips_distance, psnr, ssim
    from drivingscene.eval.reconstruction import _nanmean

    pred = pred.flatten(0, 1).permute(0, 3, 1, 2)
    target = torch.from_numpy(pair.eval_images).flatten(0, 1).permute(0, 3, 1, 2).float() / 255
    out = {"psnr": _nanmean(psnr(pred, target)), "ssim": _nanmean(ssim(pred, target))}
    out["lpips"] = _nanmean(lpips_distance(pred, target, metric=perceptual))
    dyn = torch.from_numpy(pair.eval_dynamic).flatten(0, 1)
    out["psnr_dyn"] = _nanmean(psnr(pred, target, dyn))
    out["ssim_dyn"] = _nanmean(ssim(pred, target, dyn))
    out["lpips_dyn"] = _nanmean(lpips_distance(pred, target, dyn, metric=perceptual))
    out["dynamic_share"] = float(dyn.float().mean())
    return out


@pytest.fixture(scope="module")
def scored_pair():
    """A pair of 2 cameras at 36 x 40 (large enough for the perceptual network) with moving pixels,
    a prediction and the perceptual metric."""
    from drivingscene.eval.lpips import load_perceptual

    pair = make_pair(2, 36, 40)
    rng = np.random.default_rng(1)
    pair = replace(pair, eval_dynamic=rng.uniform(size=(1, 2, 36, 40)) < 0.3)
    return pair, blend_frames(pair), load_perceptual("stlpips", "alex")


def test_scores_without_a_mask_are_bit_identical_to_before(scored_pair):
    pair, pred, perceptual = scored_pair
    assert score_frames(pred, pair, perceptual) == _old_score_novel_views(pred, pair, perceptual)


def test_masked_prediction_pixels_change_no_score(scored_pair):
    pair, pred, perceptual = scored_pair
    mask = np.ones((2, 36, 40), bool)
    mask[:, 26:, 5:30] = False  # a hood
    pair = replace(pair, valid_mask=mask)
    other = pred.clone()
    other[:, torch.from_numpy(~mask)] = torch.rand(int((~mask).sum()), 3)
    scores = score_frames(pred, pair, perceptual)
    assert scores == score_frames(other, pair, perceptual)
    assert scores["dynamic_share"] == pytest.approx(float((pair.eval_dynamic & mask).mean()))
    # an all-true mask scores every pixel: PSNR and SSIM as without one
    everything = score_frames(pred, replace(pair, valid_mask=np.ones_like(mask)), perceptual)
    unmasked = score_frames(pred, replace(pair, valid_mask=None), perceptual)
    for key in ("psnr", "ssim", "psnr_dyn", "ssim_dyn", "lpips_dyn"):
        assert everything[key] == pytest.approx(unmasked[key], rel=1e-6)


def test_depth_scores_ignore_masked_pixels():
    from types import SimpleNamespace

    from drivingscene.eval.reconstruction import score_depth

    pair = make_pair(2, 16, 20)
    rng = np.random.default_rng(2)
    depth = (pair.gt_depth * rng.uniform(0.8, 1.2, pair.gt_depth.shape)).astype(np.float32)
    mask = np.ones((2, 16, 20), bool)
    mask[:, -5:] = False
    scores = score_depth(SimpleNamespace(depth=depth), replace(pair, valid_mask=mask))
    wrong = depth.copy()
    wrong[:, ~mask] = 1000.0
    assert scores == score_depth(SimpleNamespace(depth=wrong), replace(pair, valid_mask=mask))
    assert score_depth(SimpleNamespace(depth=wrong), pair)["depth_abs_rel"] > scores["depth_abs_rel"] + 1
    # an all-true mask changes nothing
    assert score_depth(SimpleNamespace(depth=depth), pair) == score_depth(
        SimpleNamespace(depth=depth), replace(pair, valid_mask=np.ones_like(mask))
    )


def test_road_plane_depth_meets_the_ground():
    from drivingscene.data.road_plane import road_plane_depth
    from drivingscene.geometry.camera import unproject

    pair = make_pair(3, 12, 16)  # cameras level, 1.5 m above the ego's z = 0
    depth = road_plane_depth(pair, far=80.0)
    assert depth.shape == (2, 3, 12, 16) and depth.dtype == np.float32
    points = unproject(torch.from_numpy(depth[0]), torch.from_numpy(pair.intrinsics))  # [V, H, W, 3]
    ego = torch.einsum("vij,vhwj->vhwi", torch.from_numpy(pair.cam_to_ego[:, :3, :3]), points) + torch.from_numpy(
        pair.cam_to_ego[:, None, None, :3, 3]
    )
    below = depth[0] < 80
    rows = np.arange(12)[:, None] > (12 - 1) / 2  # level cameras: the rows under the principal point look down
    assert np.array_equal(below[0], np.broadcast_to(rows, (12, 16)))
    assert torch.allclose(ego[..., 2][torch.from_numpy(below)], torch.tensor(0.0), atol=1e-4)
    # a camera mounted under the plane never meets it
    cam_to_ego = pair.cam_to_ego.copy()
    cam_to_ego[:, 2, 3] = -1.5
    assert (road_plane_depth(replace(pair, cam_to_ego=cam_to_ego)) == 80).all()


def test_nearest_return_depth():
    from drivingscene.eval.baselines import nearest_return_depth

    kept = np.zeros((2, 5, 7), np.float32)
    kept[0, 0, 0], kept[0, 4, 6] = 3.0, 9.0
    out = nearest_return_depth(kept)
    assert out[0, 0, 1] == 3.0 and out[0, 4, 5] == 9.0 and out[0, 1, 1] == 3.0 and out[0, 3, 5] == 9.0
    assert out[0, 0, 0] == 3.0  # a kept return keeps its value
    assert (out[1] == 0).all()  # no returns, no prediction
