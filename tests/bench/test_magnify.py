"""`drivingscene bench magnify`: every approach scored the same way, and the default holds up where
the renderer as it was fell apart (a view four times the input's size)."""

from __future__ import annotations

import math

import pytest

from drivingscene.bench.magnify import DEFAULT, VARIANTS, score_pair
from drivingscene.methods.feedforward import load_model


@pytest.mark.gl
def test_the_default_closes_magnified_views_the_old_renderer_left_open(synth_pair_96):
    model = load_model()
    before = score_pair(model, synth_pair_96, VARIANTS[0])
    after = score_pair(model, synth_pair_96, DEFAULT)
    for scores in (before, after):
        assert {"input_views", "in_between", "x1_vs_bicubic", "x4_vs_bicubic", "x4_holes", "x4_raw_holes"} <= set(scores)
        assert all(math.isfinite(v) for v in scores.values())
    assert before["x4_holes"] > 0.2 and after["x4_holes"] < 0.01  # the screen-door, and none
    assert after["x4_vs_bicubic"] > before["x4_vs_bicubic"] + 5.0
    assert after["input_views"] > before["input_views"] + 2.0  # the colour solve
    assert after["x1_vs_bicubic"] - after["x4_vs_bicubic"] < before["x1_vs_bicubic"] - before["x4_vs_bicubic"]
