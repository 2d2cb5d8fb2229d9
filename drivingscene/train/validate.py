"""Periodic validation during training: the full inference path on held-out pairs."""

from __future__ import annotations

import math
from pathlib import Path

import torch

from drivingscene.data.frame_pair import load_frame_pair
from drivingscene.eval.reconstruction import score_input_views, score_reconstruction
from drivingscene.methods.feedforward import InferenceOptions, reconstruct
from drivingscene.models.model import DrivingSceneModel

KEYS = ("psnr", "psnr_input", "psnr_dyn", "depth_abs_rel", "depth_ms_abs_rel", "epe_dyn_rigid", "epe_dyn_total")


def validate(model: DrivingSceneModel, files: list[Path], config) -> dict[str, float]:
    """Mean of the headline scores over ``files`` (no perceptual term, to stay cheap). The networks
    alone: without the inference-time search along the rigid flow, which training does not change."""
    model.eval()
    options = InferenceOptions(use_residual=config.stage not in ("static", "depth"), amp=config.amp, search=None, objects=None)
    sums: dict[str, list[float]] = {k: [] for k in KEYS}
    for path in files:
        pair = load_frame_pair(path)
        recon = reconstruct(model, pair, options)
        scores = score_reconstruction(recon, pair, perceptual=None) | score_input_views(recon, pair)
        for k in KEYS:
            if k in scores and not math.isnan(scores[k]):
                sums[k].append(scores[k])
    torch.set_grad_enabled(True)
    return {k: round(sum(v) / len(v), 4) for k, v in sums.items() if v}
