"""Adapting the depth network to one pair at test time (refinement's ``adapt_steps``).

A copy of the model takes K Adam steps on the pair's own self-supervised stage-1 losses: L_loc,
each input image reprojected from the same camera at the other keyframe and from its
neighbouring cameras at the same keyframe with the predicted depth (per-pixel minimum over the
sources, monodepth2's auto-mask), and L_smooth (edge-aware smoothness of the mean-normalised
disparity), weighted 1 : 0.01 as in stage 1 (0.1 : 0.001); with LiDAR also the mean |log depth -
log LiDAR| where there is a return. Batch-norm statistics stay those of training (one pair is no
batch). These losses reach D only, so only D runs in the steps (`predict_depth`); P is not trained
by them, but its Gaussians follow D's new depth when the pair is reconstructed again. The original model is not modified.
"""

from __future__ import annotations

import copy
import time

import torch
import torch.nn.functional as F
from torch import Tensor

from drivingscene.data.tensors import PairTensors
from drivingscene.geometry.flow import backward_warp, rigid_flow
from drivingscene.methods.depth_sweep import neighbour_cameras
from drivingscene.methods.refine.inputs import RefineInputs, scaled_inputs
from drivingscene.methods.refine.threads import ThreadChoice, typical_step
from drivingscene.models.losses import blank_masked, reprojection_loss, sampled_from, smoothness_loss
from drivingscene.models.pipeline import predict_depth
from drivingscene.precision import resolve_amp

SMOOTH_WEIGHT = 0.01  # L_smooth relative to L_loc (stage 1: 0.001 / 0.1)
# The first gradient step's estimate before any is timed, in adaptation steps. A gradient step in
# the `cameras` blend (a rasterisation per input image's layer) took 0.9-1.35 times as long as an
# adaptation step with the losses at half size, on 176x320 procedural pairs and the real DDAD pair,
# with 1 and 2 threads (AMD EPYC, 2026-11-27, compositing compiled; 2.3-2.6 times before); the
# first step also builds the views, hence the margin.
STEP_PER_ADAPT_STEP = 1.5


def pair_tensors(inputs: RefineInputs) -> PairTensors:
    """The networks' view of the input images (no ground truth, no held-out frames)."""
    return PairTensors(
        images=inputs.images,
        intrinsics=inputs.intrinsics,
        cam_to_ego=inputs.cam_to_ego,
        cam_to_local=inputs.cam_to_local,
        local_to_world=inputs.local_to_world,
        valid_mask=inputs.valid,
    )


def location_loss(depth: Tensor, inputs: RefineInputs) -> Tensor:
    """L_loc (module docstring) for depth ``[2, V, H, W]``; masked pixels are neither targets nor
    sampled sources."""
    num_views = inputs.num_views
    targets = inputs.images.flatten(0, 1)  # [2V, 3, H, W]
    c2l = inputs.cam_to_local.flatten(0, 1)
    k = inputs.intrinsics.repeat(2, 1, 1)
    world = None if inputs.valid is None else inputs.valid.repeat(2, 1, 1)
    kf = torch.arange(2).repeat_interleave(num_views)
    cam = torch.arange(num_views).repeat(2)
    sources = [(1 - kf) * num_views + cam]
    for side in (0, 1) if num_views > 1 else ():
        sources.append(kf * num_views + torch.tensor([neighbour_cameras(inputs.cam_to_ego)[v][side] for v in cam.tolist()]))
    warped, valid, identity = [], [], []
    compared = targets
    for i, src in enumerate(sources):
        flow, z = rigid_flow(depth.flatten(0, 1), k, c2l, c2l[src], dst_intrinsics=k[src])
        image, inside = backward_warp(targets[src], flow)
        if world is not None:
            seen = sampled_from(world[src], flow)
            image, compared = blank_masked(image, targets, seen, world)
            inside = inside & seen & world
        warped.append(image)
        valid.append(inside & (z > 0.1))
        if i == 0:
            identity.append(targets[src] if world is None else blank_masked(targets[src], targets, world[src], world)[0])
    loss, _ = reprojection_loss(compared, warped, valid, identity)
    return loss


def _lidar_term(depth: Tensor, inputs: RefineInputs) -> Tensor:
    has = inputs.lidar > 0
    if inputs.valid is not None:
        has = has & inputs.valid[None]
    if not bool(has.any()):
        return depth.new_zeros(())
    return (torch.log(depth.clamp(min=1e-3)) - torch.log(inputs.lidar.clamp(min=1e-3)))[has].abs().mean()


def adapt_model(model, inputs: RefineInputs, config, clock, report, reserve_s: float) -> tuple[object, dict]:
    """A copy of ``model`` with D adapted for at most ``config.adapt_steps`` steps, each begun only
    where it and ``reserve_s`` more (the rebuild) still end within ``config.adapt_share`` of the
    budget, or, past that share, where no gradient step (``STEP_PER_ADAPT_STEP`` adaptation steps)
    would fit after the rebuild anyway: no part of the budget is left idle that a step could use.
    ``info["left_room"]``: it stopped to leave room for a gradient step (which then runs)."""
    adapted = copy.deepcopy(model).eval()  # eval: batch norm keeps its training statistics
    for p in adapted.parameters():
        p.requires_grad_(False)
    trainable = list(adapted.depth_net.parameters())
    for p in trainable:
        p.requires_grad_(True)
    optimizer = torch.optim.Adam(trainable, lr=config.adapt_lr)
    batch = pair_tensors(inputs)
    amp = resolve_amp(None, "cpu")
    small = scaled_inputs(inputs, config.adapt_scale)  # where L_loc and L_smooth are computed
    targets = small.images.flatten(0, 1)
    world = None if small.valid is None else small.valid.repeat(2, 1, 1)
    times, losses = [], []
    threads_of: list[int] = []  # each step's threads: the estimate follows the chosen setting's steps
    left_room = False  # stopped to leave a gradient step room after the rebuild
    choice = ThreadChoice(torch.get_num_threads()) if config.threads is None else None
    for step in range(config.adapt_steps):
        step_s = typical_step(choice, times, threads_of)
        if not clock.fits(step_s + reserve_s, share=config.adapt_share):
            left_room = bool(config.groups) and clock.fits(reserve_s + STEP_PER_ADAPT_STEP * step_s)
            if left_room or not clock.fits(step_s + reserve_s):
                break
        threads = choice.begin_step() if choice is not None else torch.get_num_threads()
        start = time.perf_counter()
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=amp):
            depth = predict_depth(adapted, batch).float()  # D alone: the losses do not reach P
        d = depth
        if small is not inputs:
            d = F.interpolate(depth.flatten(0, 1)[:, None], size=small.image_size, mode="area")[:, 0].view(
                2, -1, *small.image_size
            )
        loss = location_loss(d, small) + SMOOTH_WEIGHT * smoothness_loss(1.0 / d.flatten(0, 1)[:, None], targets, world)
        if config.lidar and inputs.lidar is not None:
            loss = loss + _lidar_term(depth, inputs)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        times.append(time.perf_counter() - start)
        threads_of.append(threads)
        if choice is not None:
            choice.record(threads, times[-1])
        losses.append(round(float(loss.detach()), 5))
        report(clock.fraction, f"adapting D: step {step + 1}/{config.adapt_steps}, L_loc {losses[-1]:.4f}")
    for p in adapted.parameters():
        p.requires_grad_(False)
    # the chosen setting's typical step: what the first gradient step's estimate scales
    step_s = round(typical_step(choice, times, threads_of), 3) if times else None
    info = {"steps": len(times), "step_s": step_s, "losses": losses, "left_room": left_room}
    info["threads"] = torch.get_num_threads() if choice is None else choice.threads()
    return adapted, info
