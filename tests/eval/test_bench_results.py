"""`drivingscene bench results` end to end on a real procedural pair with a tiny random model."""

from __future__ import annotations

import json

import cv2
import pytest
import torch
from safetensors.torch import save_file

from drivingscene.cli import main
from drivingscene.data import save_frame_pair
from drivingscene.models import DrivingSceneModel, ModelConfig
from drivingscene.models.depth import DepthConfig
from drivingscene.models.residual_flow import FlowConfig


@pytest.fixture
def tiny_weights(tmp_path):
    torch.manual_seed(0)
    config = ModelConfig(
        depth=DepthConfig(width=8, decoder_channels=(8, 8, 16, 16, 32)), flow=FlowConfig(channels=(8, 8, 16, 16), hidden=8)
    )
    path = tmp_path / "tiny.safetensors"
    save_file({k: v.contiguous() for k, v in DrivingSceneModel(config).state_dict().items()}, str(path))
    path.with_suffix(".json").write_text(json.dumps({"model": config.to_dict()}))
    return path


@pytest.mark.gl
def test_results_report_json_and_figure(synth_pair, tiny_weights, tmp_path):
    data = tmp_path / "test"
    data.mkdir()
    save_frame_pair(synth_pair, data / "pair_200000.npz")
    md, js, png = tmp_path / "results.md", tmp_path / "scores.json", tmp_path / "results.png"
    args = ["bench", "results", "--data", str(data), "--count", "1", "--weights", str(tiny_weights)]
    args += ["--joint-weights", str(tiny_weights), "--lpips", "stlpips", "--out", str(md), "--json", str(js), "--image", str(png)]
    assert main(args) == 0
    text = md.read_text()
    methods = ["DrivingScene (two-stage)", "static-only", "single-stage (joint training)", "oracle (GT depth + scene flow)"]
    for heading in ("all pixels", "dynamic pixels", "Depth at the keyframes", "end-point error", "ST-LPIPS"):
        assert heading in text
    assert all(m in text for m in methods)
    scores = json.loads(js.read_text())
    assert len(scores) == 4 and all(len(rows) == 1 for rows in scores.values())
    oracle = scores["oracle (GT depth + scene flow)"][0]
    assert oracle["depth_abs_rel"] < 1e-6 and oracle["psnr_dyn"] > scores["static-only (no residual flow)"][0]["psnr_dyn"]
    image = cv2.imread(str(png))
    height, width = synth_pair.image_size
    assert image.shape[0] > 2 * height and image.shape[1] > 5 * width  # 2 rows; 5 columns (frame + 4 methods)
