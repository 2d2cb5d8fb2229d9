"""Scoring a reconstruction against a frame pair's ground truth.

- novel views: the Gaussians rendered at the pair's intermediate frames (exact recorded ego poses)
  against the real frames: PSNR, SSIM and the perceptual distance, over all pixels and over
  dynamic pixels (``eval_dynamic``), by `score_frames`, which also scores the trivial baselines
  (`drivingscene.eval.baselines`);
- depth: the reconstruction's per-camera depth at both keyframes against ``gt_depth`` (0.1-80 m),
  metric and median-scaled;
- flow: end-point error of the rigid flow alone and of rigid + residual against ``gt_flow``, on
  dynamic and on static pixels (both keyframes, both directions), over non-occluded pixels as in
  KITTI's "noc": the ground-truth flow stays in the image and is forward/backward consistent (this
  also drops points that pass behind the camera, whose flow is unbounded).

Pixels outside the pair's ``valid_mask`` (ego body, hood, mounts) count in none of these.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from drivingscene.data.frame_pair import FramePair
from drivingscene.eval.lpips import PerceptualMetric
from drivingscene.eval.metrics import depth_metrics, lpips_distance, psnr, ssim
from drivingscene.gaussians.recon import Reconstruction
from drivingscene.gaussians.timing import DEFAULT_BLEND
from drivingscene.geometry.flow import forward_backward_consistency


def _nanmean(x: torch.Tensor) -> float:
    x = x.double().flatten()
    x = x[~torch.isnan(x)]
    return float(x.mean()) if x.numel() else math.nan


def score_frames(
    pred: torch.Tensor,  # [M, V, H, W, 3] in [0, 1]
    pair: FramePair,
    perceptual: PerceptualMetric | None,
) -> dict[str, float]:
    """Scores of predicted in-between frames against ``eval_images``, for methods and baselines alike.

    PSNR, SSIM (and the perceptual distance) over the pixels that see the world (``valid_mask``;
    every pixel without one), and the same over moving pixels (``eval_dynamic``) when known. The
    masked pixels of ``pred`` are first replaced by the target's, so what a method puts on the
    ego's body cannot reach a counted pixel through an SSIM window or the perceptual network's
    receptive field either; without a mask the scores are those of the metrics on the raw images.
    """
    pred = pred.flatten(0, 1).permute(0, 3, 1, 2)  # [MV, 3, H, W]
    target = torch.from_numpy(pair.eval_images).flatten(0, 1).permute(0, 3, 1, 2).float() / 255
    world = None  # [MV, H, W]
    if pair.valid_mask is not None:
        world = torch.from_numpy(pair.valid_mask)[None].expand(pair.num_eval, *pair.valid_mask.shape).flatten(0, 1)
        pred = torch.where(world[:, None], pred, target.to(pred.dtype))
    out = {"psnr": _nanmean(psnr(pred, target, world)), "ssim": _nanmean(ssim(pred, target, world))}
    if perceptual is not None:
        out["lpips"] = _nanmean(lpips_distance(pred, target, world, metric=perceptual))
    if pair.eval_dynamic is not None:
        dyn = torch.from_numpy(pair.eval_dynamic).flatten(0, 1)  # [MV, H, W]
        if world is not None:
            dyn = dyn & world
        out["psnr_dyn"] = _nanmean(psnr(pred, target, dyn))
        out["ssim_dyn"] = _nanmean(ssim(pred, target, dyn))
        if perceptual is not None:
            out["lpips_dyn"] = _nanmean(lpips_distance(pred, target, dyn, metric=perceptual))
        out["dynamic_share"] = float(dyn.float().mean())
    return out


def score_novel_views(
    recon: Reconstruction, pair: FramePair, perceptual: PerceptualMetric | None, blend: str = DEFAULT_BLEND
) -> dict[str, float]:
    """`score_frames` of the reconstruction rendered at the pair's intermediate frames."""
    from drivingscene.render.scene import render_eval_frames

    return score_frames(render_eval_frames(recon, pair, blend=blend), pair, perceptual)


def score_input_views(recon: Reconstruction, pair: FramePair, blend: str = DEFAULT_BLEND) -> dict[str, float]:
    """PSNR of the reconstruction rendered at its own keyframes (`render_input_views`) against the
    input images, over the pixels that see the world: how well the Gaussians reproduce their inputs."""
    from drivingscene.render.scene import render_input_views

    views = render_input_views(recon, pair, blend=blend).flatten(0, 1).permute(0, 3, 1, 2)
    inputs = torch.from_numpy(pair.images).flatten(0, 1).permute(0, 3, 1, 2).float() / 255
    world = torch.from_numpy(pair.world_mask()).repeat(2, 1, 1)
    return {"psnr_input": _nanmean(psnr(views, inputs, world))}


def score_depth(recon: Reconstruction, pair: FramePair) -> dict[str, float]:
    """Depth errors of ``recon.depth`` ``[2, V, H, W]`` against ``gt_depth`` on the pixels that see the
    world, metric and median-scaled, and metric AbsRel on moving and on static pixels."""
    if recon.depth is None or pair.gt_depth is None:
        return {}
    pred = torch.from_numpy(recon.depth).flatten(0, 1)
    gt = torch.from_numpy(pair.gt_depth).flatten(0, 1)
    if pair.valid_mask is not None:  # no ground truth on the ego's own body
        gt = torch.where(torch.from_numpy(pair.valid_mask).repeat(2, 1, 1), gt, torch.zeros_like(gt))
    out = {}
    for prefix, scaled in (("depth", False), ("depth_ms", True)):
        m = depth_metrics(pred, gt, median_scaling=scaled)
        for name in ("abs_rel", "sq_rel", "rmse", "a1"):
            out[f"{prefix}_{name}"] = _nanmean(getattr(m, name))
    if pair.gt_dynamic is not None:
        # Metric AbsRel on moving objects and on the rest: self-supervised depth is worst where the
        # photometric loss's static-world assumption fails, and lifting flow to 3D needs that depth.
        dyn = torch.from_numpy(pair.gt_dynamic).flatten(0, 1)
        for name, part in (("dyn", dyn), ("static", ~dyn)):
            m = depth_metrics(pred, gt, mask=part)
            out[f"depth_abs_rel_{name}"] = _nanmean(m.abs_rel)
    return out


def score_flow(recon: Reconstruction, pair: FramePair) -> dict[str, float]:
    if recon.rigid_flow is None or pair.gt_flow is None or pair.gt_dynamic is None:
        return {}
    gt_pair = torch.from_numpy(pair.gt_flow)
    gt = gt_pair.flatten(0, 1)
    dyn = torch.from_numpy(pair.gt_dynamic).flatten(0, 1)
    noc = torch.cat([forward_backward_consistency(gt_pair[k], gt_pair[1 - k]) for k in (0, 1)])
    valid = noc & (torch.from_numpy(pair.gt_depth > 0).flatten(0, 1) if pair.gt_depth is not None else True)
    if pair.valid_mask is not None:
        valid = valid & torch.from_numpy(pair.valid_mask).repeat(2, 1, 1)
    out = {}
    # total: rigid + the residual as proposed (R and the search, also where the lift keeps a pixel
    # static); applied: rigid + the residual where the pixel's Gaussian moves (what it does)
    for name, flow in (("rigid", recon.rigid_flow), ("total", recon.total_flow), ("applied", recon.applied_total_flow)):
        pred = torch.from_numpy(np.ascontiguousarray(flow)).flatten(0, 1)
        # Pool pixels over all images (images without dynamic pixels give NaN and are skipped).
        errs = (pred.double() - gt.double()).norm(dim=-1)
        out[f"epe_dyn_{name}"] = float(errs[dyn & valid].mean()) if (dyn & valid).any() else math.nan
        out[f"epe_static_{name}"] = float(errs[~dyn & valid].mean()) if (~dyn & valid).any() else math.nan
    return out


@torch.no_grad()
def score_reconstruction(
    recon: Reconstruction, pair: FramePair, perceptual: PerceptualMetric | None = None, blend: str = DEFAULT_BLEND
) -> dict[str, float]:
    """Every available score of ``recon`` on ``pair`` as a flat dict of floats (NaN = not defined)."""
    out: dict[str, float] = {"gaussians": float(len(recon.visible())), "dynamic_gaussians": float(recon.visible().dynamic.sum())}
    if pair.num_eval:
        out.update(score_novel_views(recon, pair, perceptual, blend))
    out.update(score_depth(recon, pair))
    out.update(score_flow(recon, pair))
    return out
