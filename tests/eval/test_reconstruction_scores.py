"""Scoring reconstructions: the oracle is perfect where it must be, ablations score worse."""

from __future__ import annotations

import math

import pytest

from drivingscene.eval.reconstruction import score_reconstruction
from drivingscene.methods.oracle import oracle_reconstruction


@pytest.fixture(scope="module")
def oracle_scores(synth_pair):
    return score_reconstruction(oracle_reconstruction(synth_pair), synth_pair)


@pytest.mark.gl
def test_oracle_depth_and_flow_are_exact(oracle_scores):
    assert oracle_scores["depth_abs_rel"] < 1e-6
    assert oracle_scores["epe_dyn_total"] < 1e-3 and oracle_scores["epe_static_total"] < 1e-3
    assert oracle_scores["epe_dyn_rigid"] > 1.0  # moving objects are not explained by ego motion


@pytest.mark.gl
def test_oracle_renders_the_intermediate_frame(oracle_scores):
    assert 15 < oracle_scores["psnr"] < 60 and 0 < oracle_scores["ssim"] <= 1
    assert not math.isnan(oracle_scores["psnr_dyn"])


@pytest.mark.gl
def test_static_oracle_is_worse_on_moving_objects(synth_pair, oracle_scores):
    static = score_reconstruction(oracle_reconstruction(synth_pair, use_scene_flow=False), synth_pair)
    assert static["psnr_dyn"] < oracle_scores["psnr_dyn"] - 1.0
    assert static["dynamic_gaussians"] == 0 < oracle_scores["dynamic_gaussians"]
