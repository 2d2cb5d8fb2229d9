"""``drivingscene bench objects`` (drivingscene.bench.objects): the tracking's accepted objects
against ground truth, and the recording hook of methods/object_motion.py it reads."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from drivingscene.bench.objects import BINS, object_rows, summary
from drivingscene.cli import main
from drivingscene.methods.object_motion import AcceptedObject, object_flows, recording
from tests.eval.test_bench_results import tiny_weights  # noqa: F401  (fixture)
from tests.factories import make_pair
from tests.methods.test_object_motion import _scene


def test_summary_bins_counts_and_weights_by_pixels():
    rows = [
        {"share": 0.02, "pixels": 100, "moving": 0.9, "error": 1.0, "rigid_error": 9.0},  # a true object, well matched
        {"share": 0.03, "pixels": 300, "moving": 0.0, "error": 3.0, "rigid_error": 4.0},
        {"share": 0.40, "pixels": 50, "moving": 0.1, "error": 80.0, "rigid_error": 2.0},  # carried far onto another surface
        {"share": 1.30, "pixels": 50, "moving": 0.0, "error": 120.0, "rigid_error": 2.0},  # beyond the last edge: the last bin
    ]
    bins = summary(rows)
    assert len(bins) == len(BINS) - 1 and [b["objects"] for b in bins] == [2, 0, 0, 0, 0, 2]
    first, last = bins[0], bins[-1]
    assert first["moving_objects"] == 1 and first["worse"] == 0
    assert first["error"] == pytest.approx((100 * 1.0 + 300 * 3.0) / 400) and first["rigid_error"] == pytest.approx(5.25)
    assert last["moving_objects"] == 0 and last["worse"] == 2 and last["error"] == pytest.approx(100.0)
    assert math.isnan(bins[1]["error"])


def test_object_rows_score_the_match_and_the_rigid_flow_over_its_pixels():
    gt_flow, gt_dynamic = np.zeros((2, 2, 12, 20, 2), np.float32), np.zeros((2, 2, 12, 20), bool)
    pixels = np.zeros((12, 20), bool)
    pixels[2:6, 3:9] = True
    gt_flow[0, 1][pixels] = (5.0, 0.0)
    gt_dynamic[0, 1][2:4, 3:9] = True  # half of its pixels move
    pair = replace(make_pair(num_views=2, height=12, width=20), gt_flow=gt_flow, gt_dynamic=gt_dynamic)
    warp = np.array([[1.0, 0.0, 4.0], [0.0, 1.0, 0.0]], np.float32)  # 4 px: 1 px short of the truth
    rigid = np.zeros((2, 2, 12, 20, 2), np.float32)
    (row,) = object_rows([AcceptedObject(0, 1, pixels, warp, 4.0)], rigid, pair)
    assert row == pytest.approx({"share": 4.0 / 20, "pixels": 24, "moving": 0.5, "error": 1.0, "rigid_error": 5.0})


def test_recording_lists_what_object_flows_accepts_and_nothing_outside():
    images, mask0, _, _ = _scene((17.0, 2.0))
    args = (np.zeros((*images.shape[:4], 2), np.float32), np.zeros(images.shape[:4], bool), np.full(images.shape[:4], 10.0))
    with recording() as accepted:
        _, owned = object_flows(images, *args)
    assert accepted and all(isinstance(a, AcceptedObject) for a in accepted)
    first = next(a for a in accepted if a.keyframe == 0)
    assert (first.pixels & mask0).sum() >= 0.6 * mask0.sum() and (first.pixels <= owned[0, 0]).all()
    np.testing.assert_allclose(first.warp, [[1, 0, 17], [0, 1, 2]], atol=0.5)  # pixel to pixel: the shift
    assert abs(first.motion - np.hypot(17.0, 2.0)) < 0.5
    seen = len(accepted)
    object_flows(images, *args)  # outside the block: not recorded, and the list it gave is kept
    assert len(accepted) == seen


def test_bench_objects_report(synth_pair_folder, tiny_weights, tmp_path):  # noqa: F811
    out = tmp_path / "objects.md"
    args = ["bench", "objects", "--data", str(synth_pair_folder), "--count", "1", "--weights", str(tiny_weights)]
    assert main([*args, "--out", str(out)]) == 0
    text = out.read_text()
    assert "objects accepted in 1 pairs" in text and text.count("\n| 0.") == len(BINS) - 1
    assert main([*args, "--max-motion", "0"]) == 2  # a one-line error, no traceback
