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
