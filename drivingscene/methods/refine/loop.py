"""The stages of `refine.refine`: adaptation, the depth correction, the gradient steps, and the
reconstruction they leave (Gaussians back in the world frame, per-camera maps brought up to date)."""

from __future__ import annotations

import logging
import math
import statistics
import time
from dataclasses import replace

import numpy as np
import torch
from torch import Tensor

from drivingscene.errors import DrivingSceneError
from drivingscene.gaussians.core import Gaussians
from drivingscene.gaussians.recon import Reconstruction
from drivingscene.geometry.camera import pixel_grid, project
from drivingscene.geometry.flow import forward_backward_consistency, rigid_flow
from drivingscene.geometry.scene_flow import scene_flow_from_optical_flow
from drivingscene.geometry.se3 import invert_rigid, transform_points
from drivingscene.methods.depth_sweep import corrected_depth
from drivingscene.methods.refine.adapt import STEP_PER_ADAPT_STEP
from drivingscene.methods.refine.inputs import RefineInputs
from drivingscene.methods.refine.params import GaussianRays, RefineParams
from drivingscene.methods.refine.render import view_set, views_loss
from drivingscene.methods.refine.threads import ThreadChoice, typical_step
from drivingscene.render.scene import source_axes

log = logging.getLogger(__name__)

NEAR_Z = 0.5  # as the model's rigid flow: a static point nearer than this to the other camera has none
RELIFT_THRESHOLD = 1.0 / 176  # of the image width: the model's dynamic gate, 1 px at its 96x176 input


def adapt_and_rebuild(
    model, pair, recon: Reconstruction, inputs: RefineInputs, config, clock, report, meta: dict, rebuild_s: float
) -> Reconstruction:
    """Adapt a copy of D to the pair (`refine.adapt`; ``rebuild_s`` of the budget kept for the
    reconstruction after it), then reconstruct the pair again (``recon`` as it is where no step fitted)."""
    from drivingscene.methods.feedforward import reconstruct
    from drivingscene.methods.refine.adapt import adapt_model

    adapted, info = adapt_model(model, inputs, config, clock, report, reserve_s=rebuild_s)
    meta["adapt"] = info
    if not info["steps"]:
        return recon
    report(clock.fraction, "rebuilding the reconstruction with the adapted networks")
    return reconstruct(adapted, pair)


class _Bf16(torch.nn.Module):
    """The perceptual metric under bf16 autocast where the CPU does bf16 natively."""

    def __init__(self, metric, enabled: bool):
        super().__init__()
        self.metric, self.enabled = metric, enabled

    def forward(self, x: Tensor, y: Tensor) -> Tensor:
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=self.enabled):
            return self.metric(x, y).float()


def _perceptual(weight: float):
    if weight <= 0:
        return None
    from drivingscene.eval.lpips import load_perceptual
    from drivingscene.precision import resolve_amp

    try:
        metric = load_perceptual("auto")
    except DrivingSceneError as e:  # the loss is still L2: refinement is not worth failing for it
        log.warning("refine: no perceptual metric (%s); the rendering loss is L2 only", e)
        return None
    return _Bf16(metric, resolve_amp(None, "cpu"))


def pixel_depth(params: RefineParams, shape: tuple[int, ...]) -> Tensor:
    """``[2, V, H, W]`` the Gaussians' current camera z at their source pixels (0 elsewhere)."""
    rays = params.rays
    depth = torch.zeros(int(np.prod(shape)))
    ok = rays.has_ray
    z = rays.depths * torch.exp(params.values["depth"].detach())
    depth[rays.pixels[ok]] = z[ok]
    return depth.view(shape)


def corrected_gaussians(
    local: Gaussians, rays: GaussianRays, inputs: RefineInputs, recon, config, clock, report, meta: dict
) -> Gaussians:
    """The Gaussians slid along their rays to the depth the sweep (and LiDAR) corrected, with the
    dynamic ones' flows lifted again with that depth (`relift_flows`); unchanged if the sweep stops."""
    report(clock.fraction, "searching depth along the rays (plane sweep)")
    start = time.perf_counter()
    params = RefineParams(local, rays, ())
    shape = (2, inputs.num_views, *inputs.image_size)
    result = corrected_depth(
        inputs.images,
        inputs.intrinsics,
        inputs.cam_to_local,
        inputs.cam_to_ego,
        pixel_depth(params, shape),
        inputs.valid,
        inputs.lidar if config.lidar else None,
        config.sweep,
        should_stop=clock.stopped_at(config.sweep_share),
    )
    if result is None:
        meta["sweep"] = {"seconds": round(time.perf_counter() - start, 3), "stopped": True}
        return local
    target = result.depth.flatten()[rays.pixels.clamp(min=0)]
    ok = rays.has_ray & (target > 0) & (rays.depths > 0)
    params.set_depth(torch.where(ok, torch.log(target.clamp(min=1e-3) / rays.depths.clamp(min=1e-3)), torch.zeros_like(target)))
    with torch.no_grad():
        moved = params.gaussians()
    relifted = 0
    if recon.rigid_flow is not None and recon.residual_flow is not None and bool(result.corrected.any()):
        moved, relifted = relift_flows(moved, rays, result.depth, torch.from_numpy(recon.total_flow), result.corrected, inputs)
    meta["sweep"] = {
        "seconds": round(time.perf_counter() - start, 3),
        "corrected_images": int(result.corrected.sum()),
        "confirmed_share": round(float(result.confirmed.float().mean()), 4),
        "dynamic_made_static": relifted,
    }
    return moved


def relift_flows(
    gaussians: Gaussians,  # local frame, at the corrected depth
    rays: GaussianRays,
    depth: Tensor,  # [2, V, H, W] corrected depth
    total_flow: Tensor,  # [2, V, H, W, 2] the reconstruction's optical flow (rigid + residual)
    corrected: Tensor,  # [2, V] bool: images whose depth changed
    inputs: RefineInputs,
) -> tuple[Gaussians, int]:
    """Dynamic Gaussians of corrected images with their flow lifted again from the same optical flow
    and the corrected depth at both ends. Those whose optical flow the corrected rigid flow now
    explains (within 1 pixel at the model's 176-pixel-wide input: ``RELIFT_THRESHOLD`` of the width)
    become static; those that still move take the new lift where it is defined (the flow lands in
    the other image on a surface, and forward and backward flows agree, as the model's lift asks)
    and keep their flow elsewhere. Static Gaussians stay static. Returns the Gaussians and how many
    became static."""
    c2l = inputs.cam_to_local
    width = inputs.image_size[1]
    lifted, usable, still = [], [], []
    for k in (0, 1):
        sf, valid = scene_flow_from_optical_flow(depth[k], depth[1 - k], total_flow[k], inputs.intrinsics, c2l[k], c2l[1 - k])
        rigid, _ = rigid_flow(depth[k], inputs.intrinsics, c2l[k], c2l[1 - k])
        lifted.append(sf)
        usable.append(valid & forward_backward_consistency(total_flow[k], total_flow[1 - k]))
        still.append((total_flow[k] - rigid).norm(dim=-1) <= RELIFT_THRESHOLD * width)
    sf, usable, still = torch.stack(lifted).flatten(0, 3), torch.stack(usable).flatten(), torch.stack(still).flatten()
    image = gaussians.keyframes * inputs.num_views + gaussians.cameras.clamp(min=0)
    chosen = gaussians.dynamic & rays.has_ray & corrected.flatten()[image]
    pixel = rays.pixels.clamp(min=0)
    to_static, to_lift = chosen & still[pixel], chosen & ~still[pixel] & usable[pixel]
    flows = torch.where(to_lift[:, None], sf[pixel], gaussians.flows)
    flows = torch.where(to_static[:, None], torch.zeros_like(flows), flows)
    return replace(gaussians, flows=flows), int(to_static.sum())


def _view_batches(num_views: int, per_step: int, generator: torch.Generator):
    """Endless batches of flat view indices (k * V + v): the keyframes alternate, and each takes
    ``per_step`` of its cameras from a shuffled cycle over them. One keyframe per step renders
    in one rasterizer call when its cameras share a capture time (the per-Gaussian work, which
    dominates, is then done once)."""
    per_step = min(per_step, num_views)
    cycles = [[], []]
    k = int(torch.randint(2, (1,), generator=generator))
    while True:
        batch = []
        while len(batch) < per_step:
            if not cycles[k]:
                cycles[k] = torch.randperm(num_views, generator=generator).tolist()
            v = cycles[k].pop()
            if k * num_views + v not in batch:
                batch.append(k * num_views + v)
        yield batch
        k = 1 - k


def gradient_steps(params: RefineParams, inputs: RefineInputs, recon, config, clock, report, meta: dict) -> None:
    """Adam on the groups until the budget, ``should_stop`` or ``max_steps`` (module docstring of `refine`)."""
    perceptual = _perceptual(config.lpips_weight)
    optimizer = torch.optim.Adam([{"params": [params.parameters(g)], "lr": config.learning_rate(g)} for g in params.groups])
    generator = torch.Generator().manual_seed(config.seed)
    batches = _view_batches(inputs.num_views, config.views_per_step, generator)
    visible = None if recon.hidden is None else ~recon.hidden
    cache: dict[float, object] = {}
    times, losses = [], []
    # Before any step is timed, the adaptation's step (a forward and backward pass over the pair)
    # scaled by `STEP_PER_ADAPT_STEP` says whether one fits: without it the first step overran 30 s
    # budgets by up to 3 s once the adaptation had used most of them. Where the adaptation stopped
    # to leave room for one (by the same estimate), the first step runs: the decision is made once,
    # before the rebuild, whose time varies.
    adapt = meta.get("adapt") or {}
    first = 0.0 if adapt.get("left_room") else STEP_PER_ADAPT_STEP * float(adapt.get("step_s") or 0.0)
    choice = ThreadChoice(torch.get_num_threads()) if config.threads is None else None
    threads_of: list[int] = []  # each step's threads: the estimate follows the chosen setting's steps
    while config.max_steps is None or len(times) < config.max_steps:
        estimate = typical_step(choice, times, threads_of) if times else first
        if not clock.fits(estimate):
            break
        start = time.perf_counter()
        progress = max(clock.fraction, len(times) / config.max_steps if config.max_steps else 0.0)
        if config.decay:
            factor = 0.1 + 0.9 * 0.5 * (1 + math.cos(math.pi * min(progress, 1.0)))
            for group, name in zip(optimizer.param_groups, params.groups):
                group["lr"] = factor * config.learning_rate(name)
        scale = config.scale_at(clock.fraction)
        if scale not in cache:
            cache[scale] = view_set(inputs, recon.sky_sh, scale, config.blend, local_axes(recon, inputs))
        index = next(batches)
        threads_of.append(choice.begin_step() if choice is not None else torch.get_num_threads())
        gaussians = params.gaussians()
        if visible is not None:
            gaussians = gaussians.index(visible)
        loss, terms = views_loss(
            gaussians,
            cache[scale],
            index,
            perceptual,
            lpips_weight=config.lpips_weight,
            lidar_weight=config.lidar_weight if config.lidar else 0.0,
            max_layers=config.max_layers,
        )
        before = params.state()
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        if not (bool(torch.isfinite(loss)) and params.finite()):
            params.load(before)
            log.warning("refine: a step produced non-finite values; keeping the previous step")
            break
        times.append(time.perf_counter() - start)
        if choice is not None:
            choice.record(threads_of[-1], times[-1])
        losses.append(float(loss.detach()))
        report(clock.fraction, f"step {len(times)}: loss {losses[-1]:.4f} at {scale:g}x, {times[-1]:.2f} s per step")
        log.debug("refine step %d: %s", len(times), terms)
    meta.update(
        threads=choice.threads() if choice is not None and times else torch.get_num_threads(),
        steps=len(times),
        step_s=round(statistics.median(times), 3) if times else None,
        step_times=[round(t, 3) for t in times],
        losses=[round(v, 5) for v in losses],
        views_per_step=config.views_per_step,
    )


def local_axes(recon, inputs: RefineInputs) -> Tensor:
    """``[2, V, 3]`` the input cameras' optical axes in the pair's local frame (the "cameras" blend)."""
    rotation = inputs.world_to_local[:3, :3].float()
    return source_axes(recon) @ rotation.T


def _clamped_destinations(points: Tensor, height: int, width: int) -> Tensor:
    """Pixel positions ``[..., 2]`` clamped to the image's size beyond each side (-W .. 2W - 1, -H .. 2H - 1)."""
    low, high = points.new_tensor([-width, -height]), points.new_tensor([2 * width - 1, 2 * height - 1])
    return torch.minimum(torch.maximum(points, low), high)


def _rigid_flow_maps(depth: Tensor, inputs: RefineInputs) -> Tensor:
    """``[2, V, H, W, 2]`` rigid flow of each keyframe's depth into the other keyframe, 0 where a
    static point would pass behind the other camera (as the model's) and where the depth is 0."""
    c2l = inputs.cam_to_local
    height, width = depth.shape[-2:]
    flows = []
    for k in (0, 1):
        flow, z = rigid_flow(depth[k], inputs.intrinsics, c2l[k], c2l[1 - k])
        grid = pixel_grid(height, width)
        dest = _clamped_destinations(grid + flow, height, width)
        flows.append(torch.where(((z < NEAR_Z) | (depth[k] <= 0))[..., None], torch.zeros_like(flow), dest - grid))
    return torch.stack(flows)


def _residual_flow_maps(params: RefineParams, gaussians, inputs: RefineInputs, shape) -> Tensor:
    """``[2, V, H, W, 2]``: at each dynamic Gaussian's pixel, where its flow takes it in the other
    keyframe's image minus where a static point would land; 0 elsewhere, and where either point is
    nearer than ``NEAR_Z`` to the other camera or behind it (no pixel there), both destinations
    clamped to the image's size on every side (as the rigid flow)."""
    out = torch.zeros(int(np.prod(shape)), 2)
    index = params.dynamic[params.rays.has_ray[params.dynamic]]
    if index.numel():
        g = gaussians
        other = (1 - g.keyframes[index]) * inputs.num_views + g.cameras[index]
        to_cam = invert_rigid(inputs.cam_to_local.flatten(0, 1))[other]
        k = inputs.intrinsics[g.cameras[index]]
        moved_cam = transform_points(to_cam, (g.means[index] + g.flows[index])[:, None])
        still_cam = transform_points(to_cam, g.means[index][:, None])
        moved = _clamped_destinations(project(moved_cam, k)[0], *shape[-2:])  # as the rigid flow's
        still = _clamped_destinations(project(still_cam, k)[0], *shape[-2:])
        seen = (moved_cam[..., 2] >= NEAR_Z) & (still_cam[..., 2] >= NEAR_Z)
        out[params.rays.pixels[index]] = torch.where(seen[..., None], moved - still, torch.zeros_like(moved))[:, 0]
    return out.view(*shape, 2)


def refined_reconstruction(recon: Reconstruction, params: RefineParams, inputs: RefineInputs, meta: dict) -> Reconstruction:
    """The refined Gaussians in the world frame, with the per-camera maps that depend on them
    (depth, rigid and residual flow) brought up to date where the reconstruction has them."""
    with torch.no_grad():
        local = params.gaussians().detach()
        world = local.transform(inputs.local_to_world)
        shape = (2, inputs.num_views, *inputs.image_size)
        depth = rigid = residual = None
        if recon.depth is not None:
            depth = torch.from_numpy(recon.depth.copy()).view(-1)
            moved = pixel_depth(params, shape).view(-1)
            ok = params.rays.pixels[params.rays.has_ray]
            depth[ok] = moved[ok]
            depth = depth.view(shape)
        if recon.rigid_flow is not None and depth is not None:
            rigid = _rigid_flow_maps(depth, inputs).numpy().astype(np.float32)
        if recon.residual_flow is not None:
            residual = _residual_flow_maps(params, local, inputs, shape).numpy().astype(np.float32)
    method = str(recon.meta.get("method", "?"))
    return Reconstruction(
        gaussians=world,
        intrinsics=recon.intrinsics,
        cam_to_ego=recon.cam_to_ego,
        ego_to_world=recon.ego_to_world,
        timestamps=recon.timestamps,
        camera_names=recon.camera_names,
        image_size=recon.image_size,
        sky_sh=recon.sky_sh,
        hidden=recon.hidden,
        images=recon.images,
        depth=None if depth is None else depth.numpy().astype(np.float32),
        rigid_flow=rigid if rigid is not None else recon.rigid_flow,
        residual_flow=residual if residual is not None else recon.residual_flow,
        valid_mask=recon.valid_mask,
        meta={**recon.meta, "method": method if method.endswith("+refine") else f"{method}+refine", "refinement": meta},
    )
