"""What ``bench refine`` and its choices (``bench/refine_choices.py``) share: the keyframes'
re-render score, a reconstruction with its depth scaled, and the report's cell helpers."""

from __future__ import annotations

import math

import numpy as np
import torch


def scaled_depth(recon, pair, factor: float):
    """``recon`` with every Gaussian slid along its ray to ``factor`` times its depth (and its depth map)."""
    from dataclasses import replace

    from drivingscene.methods.refine.inputs import refine_inputs
    from drivingscene.methods.refine.params import RefineParams, gaussian_rays

    if factor == 1.0:
        return recon
    inputs = refine_inputs(pair)
    local = recon.gaussians.transform(inputs.world_to_local)
    params = RefineParams(local, gaussian_rays(local, inputs.cam_to_local, inputs.intrinsics, inputs.image_size), ())
    params.set_depth(torch.full((len(local),), math.log(factor)))
    with torch.no_grad():
        moved = params.gaussians().transform(inputs.local_to_world)
    depth = None if recon.depth is None else (recon.depth * factor).astype(np.float32)
    return replace(recon, gaussians=moved, depth=depth)


def keyframe_psnr(recon, pair) -> float:
    from drivingscene.bench.real import _images, image_scores, render_keyframes

    mask = None if pair.valid_mask is None else torch.from_numpy(pair.world_mask())[None].expand(2, *pair.valid_mask.shape)
    scores = image_scores(render_keyframes(recon, pair), _images(pair.images), mask, None, pair.num_views)
    return float(np.nanmean(scores["psnr"]))


def _mean(rows: list[dict], key: str) -> float:
    vals = [r[key] for r in rows if r.get(key) is not None and not math.isnan(r[key])]
    return sum(vals) / len(vals) if vals else math.nan


def _fmt(x: float, fmt: str) -> str:
    return "–" if x is None or (isinstance(x, float) and math.isnan(x)) else fmt.format(x)
