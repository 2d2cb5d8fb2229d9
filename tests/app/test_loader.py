"""Opening files: scene.npz through the model (a tiny random one) or the oracle, recon.npz, PLY files
(ours and other tools'), missing weights, bad files; the background job and its progress."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from drivingscene_view.loader import LoadJob, MissingWeightsError, open_path
from safetensors.torch import save_file

from drivingscene.data import save_frame_pair
from drivingscene.errors import InputError
from drivingscene.export.ply import write_ply
from drivingscene.gaussians.recon import save_reconstruction
from drivingscene.models import DrivingSceneModel, ModelConfig
from drivingscene.models.depth import DepthConfig
from tests.app.scenes import random_gaussians, street_recon
from tests.factories import make_pair


@pytest.fixture
def scene_file(tmp_path):
    return save_frame_pair(make_pair(num_views=2, height=32, width=48), tmp_path / "scene.npz")


@pytest.fixture
def tiny_weights(tmp_path):
    """A randomly initialised small model saved the way the trained one will be (weights + JSON config)."""
    torch.manual_seed(0)
    config = ModelConfig(depth=DepthConfig(width=8, decoder_channels=(8, 8, 16, 16, 32)))
    path = tmp_path / "tiny.safetensors"
    save_file({k: v.contiguous() for k, v in DrivingSceneModel(config).state_dict().items()}, str(path))
    path.with_suffix(".json").write_text(json.dumps({"model": config.to_dict()}))
    return path


def test_scene_through_the_model(scene_file, tiny_weights):
    steps = []
    loaded = open_path(scene_file, "model", tiny_weights, lambda f, m: steps.append(m))
    recon = loaded.recon
    assert loaded.info["kind"] == "scene" and loaded.info["method"] == "drivingscene"
    assert len(recon.gaussians) > 0 and recon.depth.shape == (2, 2, 32, 48)
    assert recon.rigid_flow is not None and recon.residual_flow is not None
    assert any("model" in s for s in steps)
    auto = open_path(scene_file, "auto", tiny_weights)  # auto = the model when the weights exist
    assert auto.info["method"] == "drivingscene"


def test_missing_weights_offer_the_oracle(scene_file, tmp_path):
    with pytest.raises(MissingWeightsError, match="model weights not found") as info:
        open_path(scene_file, "auto", tmp_path / "none.safetensors")
    assert info.value.pair.gt_depth is not None  # the UI offers the oracle from this pair
    assert "\n" not in str(info.value)
    oracle = open_path(scene_file, "oracle")
    assert oracle.info["method"] == "oracle" and len(oracle.recon.gaussians) > 0


def test_recon_and_ply_files(tmp_path):
    recon = street_recon()
    loaded = open_path(save_reconstruction(recon, tmp_path / "r.npz"))
    assert loaded.info["kind"] == "recon" and len(loaded.recon.gaussians) == len(recon.gaussians)
    ours = open_path(write_ply(recon.gaussians, tmp_path / "ours.ply", "dynamic"))
    assert ours.info["up"] == "z" and ours.recon.num_views == 0
    torch.testing.assert_close(ours.recon.gaussians.flows, recon.gaussians.flows)
    foreign = tmp_path / "foreign.ply"
    text = write_ply(random_gaussians(50), tmp_path / "x.ply").read_bytes().replace(b"comment DrivingScene frame z-up\n", b"")
    foreign.write_bytes(text)
    other = open_path(foreign)
    assert other.info["up"] == "-y" and len(other.recon.gaussians) == 50


@pytest.mark.parametrize("content, match", [(b"not a zip", "npz"), (None, "file not found")])
def test_bad_files_are_one_line_errors(tmp_path, content, match):
    path = tmp_path / "bad.npz"
    if content is not None:
        path.write_bytes(content)
    with pytest.raises(InputError) as info:
        open_path(path)
    assert "\n" not in str(info.value) and str(path) in str(info.value)


def test_points_ply_is_rejected_with_a_hint(tmp_path):
    path = write_ply(random_gaussians(20), tmp_path / "points.ply", "points")
    with pytest.raises(InputError, match="point cloud"):
        open_path(path)


def test_model_load_reports_each_stage_in_order(scene_file, tmp_path):
    """The progress box names the model's stages as they start, with the share of them done."""
    from tests.reliability.corpus import tiny_weights

    seen = []
    open_path(scene_file, "model", tiny_weights(tmp_path), lambda fraction, message: seen.append((fraction, message)))
    staged = [(f, m) for f, m in seen if f is not None]
    assert [f for f, _ in staged] == [0.0, 0.25, 0.5, 0.75, 1.0]
    assert staged[0][1].startswith("depth and Gaussian parameters") and staged[1][1].startswith("matching the keyframes")
    assert all("cameras, " in m for _, m in staged)  # the camera count and the precision stay in view


def test_background_job_reports_progress_and_errors(scene_file, tmp_path):
    job = LoadJob("oracle", lambda progress: open_path(scene_file, "oracle", None, progress))
    assert job.wait(60)
    assert job.error is None and job.result.info["method"] == "oracle"
    failing = LoadJob("missing", lambda progress: open_path(tmp_path / "nope.npz", "auto", None, progress))
    assert failing.wait(10)
    assert failing.result is None and "file not found" in str(failing.error)
    assert np.isfinite(failing.elapsed)
