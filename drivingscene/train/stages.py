"""One training step per stage, as an ``nn.Module`` whose forward returns the loss (so it can be
wrapped in DistributedDataParallel).

- static:  D and P on both keyframes. L_loc reprojects every image from the same camera at the
  other keyframe (temporal) and from its neighbouring cameras at the same time (spatial).
  L_render renders Gaussians into views they did not come from: the intermediate frame of the
  training pair when it has one, else the other keyframe.
- dynamic: D and P frozen; R on the rigid flow. L_warp and L_consist on the total flow, L_render
  of Gaussians moved by the lifted flow to the intermediate time (or to the other keyframe).
- joint:   everything trained together from the start (the single-stage ablation).
- depth:   D alone with stage 1's losses, P and R frozen: more depth training for a shipped model
  without undoing P's fine-tuning below (not in the paper, docs/training.md).
- gaussians: D and R frozen; P alone on L_render, with the Gaussians moved by the lifted flow as
  at inference (not in the paper: a fine-tuning of P after stage 2, docs/training.md).

L_render's targets come in turn (``TrainConfig.render_views``): the training pair's intermediate
frame ("eval"), the other keyframe from one keyframe's Gaussians ("cross": what a keyframe's
Gaussians did not see), and a keyframe's own input views from both keyframes' Gaussians
("input": what inference renders there, so that P does not blur the views it came from). Views
with both keyframes' Gaussians are blended as ``render_blend`` ("layers", as at inference).

Pixels off the pair's ``valid_mask`` (ego body, hood) are in no loss: not as targets, not as
sampled sources, and they make no Gaussian and do not colour the sky (as at inference).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from drivingscene.data.tensors import PairTensors
from drivingscene.errors import InputError
from drivingscene.geometry.camera import pixel_grid
from drivingscene.geometry.flow import backward_warp, forward_backward_consistency, rigid_flow
from drivingscene.geometry.se3 import invert_rigid
from drivingscene.models.lift import LiftConfig, MotionSearchConfig, lift_scene_flow, search_motion, sky_mask
from drivingscene.models.losses import (
    blank_masked,
    consistency_loss,
    half_moving_half_static,
    render_loss,
    reprojection_loss,
    sampled_from,
    search_distillation_loss,
    smoothness_loss,
    supervised_depth_loss,
    supervised_flow_loss,
    warp_loss,
)
from drivingscene.models.matching import neighbour_views
from drivingscene.models.model import DrivingSceneModel
from drivingscene.models.pipeline import FlowPrediction, StaticPrediction, assemble, predict_flow, predict_static
from drivingscene.precision import resolve_amp
from drivingscene.render.scene import render_gaussians
from drivingscene.render.sky import fit_sky_from_pixels
from drivingscene.train.augment import jitter_images
from drivingscene.train.config import TrainConfig

# Weight of the supervised depth of D's monocular and matching parts (each alone) beside the
# supervised depth of their combination.
AUX_DEPTH = 0.5
# Weight of the gate's own target (inside the auxiliary terms): open where matching is nearer the truth.
GATE_WEIGHT = 0.2
# Lift every consistent pixel while training so L_render reaches R everywhere; inference gates
# small residuals to static (LiftConfig default).
TRAIN_LIFT = LiftConfig(dynamic_threshold_px=0.0)


def _world(batch: PairTensors) -> Tensor | None:
    """``[2V, H, W]`` bool: the pixels of both keyframes' images that see the world (None: all)."""
    return None if batch.valid_mask is None else batch.valid_mask.repeat(2, 1, 1)


def _masked_warp(
    sources: Tensor,  # [B, 3, H, W]
    targets: Tensor,  # [B, 3, H, W]
    flow: Tensor,  # [B, H, W, 2] target -> source, pixels
    source_world: Tensor | None,  # [B, H, W] bool: sources' pixels that see the world (None: all)
    target_world: Tensor | None,  # [B, H, W] bool: targets' pixels that see the world
) -> tuple[Tensor, Tensor, Tensor]:
    """``sources`` warped into the targets, the targets, and where the two may be compared
    ``[B, H, W]``: inside the source, and with masks, a target pixel that sees the world sampled
    only from source pixels that do (images blanked elsewhere by `blank_masked`)."""
    warped, inside = backward_warp(sources, flow)
    if source_world is None:
        return warped, targets, inside
    seen = sampled_from(source_world, flow)
    warped, targets = blank_masked(warped, targets, seen, target_world)
    return warped, targets, inside & seen & target_world


def _source_sets(batch: PairTensors) -> list[tuple[Tensor, Tensor]]:
    """Per source kind, (keyframe index [2V], camera index [2V]) of the source of each target."""
    num_views = batch.num_views
    kf = torch.arange(2).repeat_interleave(num_views)
    cam = torch.arange(num_views).repeat(2)
    sets = [(1 - kf, cam)]  # temporal
    neighbours = neighbour_views(batch.cam_to_ego)
    for side in range(2 if neighbours else 0):
        sets.append((kf, torch.tensor([neighbours[v][side] for v in cam.tolist()])))
    return sets


class Bf16Metric(nn.Module):
    """A perceptual metric run under bf16 autocast (its features are normalised in float32);
    about 1.3x cheaper forward and backward on CPU than float32, for a loss term weighted 0.05."""

    def __init__(self, metric: nn.Module):
        super().__init__()
        self.metric = metric

    def forward(self, x: Tensor, y: Tensor) -> Tensor:
        with torch.autocast("cpu", dtype=torch.bfloat16):
            return self.metric(x, y).float()


class TrainStep(nn.Module):
    def __init__(self, model: DrivingSceneModel, config: TrainConfig, perceptual: nn.Module | None):
        super().__init__()
        self.model = model
        self.config = config
        self.amp = resolve_amp(config.amp, "cpu")  # `train` passes it resolved; None: this machine's choice
        self.perceptual = Bf16Metric(perceptual) if perceptual is not None and self.amp else perceptual

    def forward(self, batch: PairTensors, step: int) -> tuple[Tensor, dict[str, Tensor]]:
        stage = self.config.stage
        amp = torch.autocast("cpu", dtype=torch.bfloat16, enabled=self.amp)
        terms: dict[str, Tensor] = {}
        if stage == "gaussians":
            return self.gaussian_terms(batch, step, amp)
        if stage == "dynamic":
            self.model.depth_net.eval()
            self.model.gaussian_head.eval()
            with torch.no_grad(), amp:
                static = predict_static(self.model, batch)
        else:
            if stage == "depth":  # the frozen networks run as at inference, like the other stages' frozen ones
                self.model.gaussian_head.eval()
                self.model.flow_net.eval()
            with amp:
                static = predict_static(self.model, batch, self.jittered(batch, step))
            terms.update(self.static_terms(static, batch, step))
        if stage not in ("static", "depth"):
            terms.update(self.dynamic_terms(static, batch, step))
        w = self.config.weights
        weight = {
            "loc": w.loc,
            "smooth": w.smooth,
            "render": w.render,
            "warp": w.warp,
            "consist": w.consist,
            "flow_sup": w.flow_sup,
            "depth_sup": w.depth_sup,
            "search_sup": w.search_sup,
        }
        loss = sum(weight[k] * v for k, v in terms.items() if k in weight)
        return loss, terms

    def jittered(self, batch: PairTensors, step: int) -> Tensor | None:
        """D's input images with the run's photometric jitter (`train.augment`), drawn from the
        run's seed and the step (a resumed run draws the same); None without jitter."""
        if self.config.input_jitter <= 0 or not self.training:
            return None
        generator = torch.Generator().manual_seed(self.config.seed * 1_000_003 + step)
        return jitter_images(batch.images, self.config.input_jitter, generator)

    # -- stage 1 ---------------------------------------------------------------------------
    def static_terms(self, static: StaticPrediction, batch: PairTensors, step: int) -> dict[str, Tensor]:
        out_depths = static.depth_output.depths
        targets = batch.images.flatten(0, 1).float()  # [2V, 3, H, W]
        loc = sum(self.location_loss(d.unflatten(0, (2, batch.num_views)), batch, targets) for d in out_depths) / len(out_depths)
        world = _world(batch)
        smooth = sum(
            smoothness_loss(disp.float(), targets, world) / (2**s) for s, disp in enumerate(static.depth_output.disparities)
        )
        if static.depth_output.matching is not None:  # the corrected depth too (the correction field is D's)
            smooth = smooth + smoothness_loss(1.0 / static.depth_output.depth.float()[:, None], targets, world)
        terms = {"loc": loc, "smooth": smooth}
        if self.config.weights.depth_sup > 0:
            terms.update(self.depth_supervision(static, batch))
        if step % self.config.render_every == 0:
            terms["render"] = self.render_term(static, batch, step, scene_flow=None)
        return terms

    def depth_supervision(self, static: StaticPrediction, batch: PairTensors) -> dict[str, Tensor]:
        """L_depth_sup of D's depth at every scale and, with matching, of its two parts on their
        own (weight ``AUX_DEPTH``): the monocular depths and the matching depth, so that each stays a
        depth estimator the gate can choose between (models/depth.py)."""
        if batch.gt_depth is None:
            raise InputError("--depth-supervision: the training pairs carry no gt_depth (synthetic pairs do)")
        gt, dyn = batch.gt_depth.float(), batch.gt_dynamic
        if batch.valid_mask is not None:  # 0: no ground truth
            gt = torch.where(batch.valid_mask, gt, torch.zeros_like(gt))
        dyn = torch.zeros_like(gt, dtype=torch.bool) if dyn is None else dyn

        def sup(depths: list[Tensor], truth: Tensor = gt) -> Tensor:
            return sum(supervised_depth_loss(d.float().unflatten(0, (2, batch.num_views)), truth, dyn) for d in depths) / len(
                depths
            )

        out = static.depth_output
        terms = {"depth_sup": sup(out.depths)}
        if out.matching is not None:
            terms["depth_sup_mono"] = sup(out.mono_depths)
            # the matching depth only where some source sweeps across its image (elsewhere it is unused)
            size = gt.shape[-2:]
            informative = F.interpolate(out.matching.informative.float(), size=size, mode="nearest")[:, 0] > 0.5
            terms["depth_sup_match"] = sup([out.match_depth], torch.where(informative.view_as(gt), gt, torch.zeros_like(gt)))
            terms["gate_bce"] = gate_loss(out, gt.flatten(0, 1), dyn.flatten(0, 1))
            aux = terms["depth_sup_mono"] + terms["depth_sup_match"] + GATE_WEIGHT * terms["gate_bce"]
            terms["depth_sup"] = terms["depth_sup"] + AUX_DEPTH * aux
            terms["gate"] = out.matching.gate.detach().mean()
        return terms

    def location_loss(self, depth: Tensor, batch: PairTensors, targets: Tensor) -> Tensor:
        """L_loc for all 2V targets ``[2V, 3, H, W]`` with depth ``[2, V, H, W]``; with a
        ``valid_mask``, only target pixels that see the world, sampled only from source pixels that do."""
        c2l = batch.cam_to_local.flatten(0, 1)  # [2V, 4, 4]
        k = batch.intrinsics.repeat(2, 1, 1)
        num_views = batch.num_views
        world = _world(batch)  # [2V, H, W]
        warped, valid, identity = [], [], []
        compared = targets
        for i, (src_kf, src_cam) in enumerate(_source_sets(batch)):
            src = src_kf * num_views + src_cam
            flow, z = rigid_flow(depth.flatten(0, 1).float(), k, c2l, c2l[src], dst_intrinsics=k[src])
            source_world = None if world is None else world[src]
            image, compared, inside = _masked_warp(targets[src], targets, flow, source_world, world)
            warped.append(image)
            valid.append(inside & (z > 0.1))
            if i == 0:  # the unwarped source, for the auto-mask
                identity.append(targets[src] if world is None else blank_masked(targets[src], targets, source_world, world)[0])
        loss, _ = reprojection_loss(compared, warped, valid, identity)
        return loss

    # -- rendering, both stages --------------------------------------------------------------
    def render_term(self, static: StaticPrediction, batch: PairTensors, step: int, scene_flow: Tensor | None) -> Tensor:
        """Gaussians rendered into views they did not come from (module docstring)."""
        ref_focal = self.model.config.depth.ref_focal
        sky = sky_pixels = sky_mask(static.depth, batch.intrinsics, ref_focal, TRAIN_LIFT)
        if batch.valid_mask is not None:  # off-world pixels: no Gaussian, no sky colour (as at inference)
            sky_pixels, sky = sky & batch.valid_mask, sky | ~batch.valid_mask
        height, width = batch.image_size
        with torch.no_grad():
            sky_sh = fit_sky_from_pixels(batch.images, sky_pixels, batch.cam_to_local.double(), batch.intrinsics)
        views = [v for v in self.config.render_views if v != "eval" or batch.eval_images is not None] or ["cross"]
        view, turn = views[step % len(views)], step // len(views)
        blend = self.config.render_blend
        if view == "eval":
            m = turn % batch.eval_images.shape[0]
            gaussians = assemble(static, batch, sky, scene_flow)
            t, cams, target = batch.eval_times[m], batch.eval_cam_to_local[m], batch.eval_images[m]
        else:
            k = turn % 2
            if view == "cross":  # keyframe k from the other keyframe's Gaussians
                gaussians, blend = assemble(static, batch, sky, scene_flow, keyframes=(1 - k,)), "all"
            else:  # keyframe k's input views from both keyframes' Gaussians
                gaussians = assemble(static, batch, sky, scene_flow)
            t, cams, target = float(k), batch.cam_to_local[k], batch.images[k]
        out = render_gaussians(gaussians, t, invert_rigid(cams), batch.intrinsics, height, width, sky_sh=sky_sh, blend=blend)
        pred = out.colors.permute(0, 3, 1, 2).clamp(0, 1)
        return render_loss(pred, target, self.perceptual, self.config.weights.render_lpips, batch.valid_mask)

    # -- P alone, after stage 2 ----------------------------------------------------------------
    def gaussian_terms(self, batch: PairTensors, step: int, amp) -> tuple[Tensor, dict[str, Tensor]]:
        """L_render of P's Gaussians moved by the frozen D and R's lifted flow (as at inference)."""
        self.model.depth_net.eval()
        self.model.flow_net.eval()
        with amp:
            static = predict_static(self.model, batch)  # D's parameters are frozen: grads reach P only
        with torch.no_grad():
            depth = static.depth.float()
            scene_flow = self.scene_flow(depth, predict_flow(self.model, batch, depth), batch)
        render = self.render_term(static, batch, step, scene_flow)
        return self.config.weights.render * render, {"render": render}

    # -- stage 2 ---------------------------------------------------------------------------
    def scene_flow(self, depth: Tensor, flow: FlowPrediction, batch: PairTensors) -> Tensor:
        """R's total flow lifted to the Gaussians' world displacement, as at inference: sky and
        off-world pixels (``valid_mask``) do not move."""
        sky = sky_mask(depth, batch.intrinsics, self.model.config.depth.ref_focal, TRAIN_LIFT)
        if batch.valid_mask is not None:
            sky = sky | ~batch.valid_mask
        scene_flow, _ = lift_scene_flow(depth, flow.total, flow.residual, sky, batch, TRAIN_LIFT)
        return scene_flow

    def dynamic_terms(self, static: StaticPrediction, batch: PairTensors, step: int) -> dict[str, Tensor]:
        depth = static.depth.float()
        # R in float32: its cost volumes and small convolutions gain nothing from bf16 on CPU, and
        # autocast's per-call weight casts cost more than they save.
        flow = predict_flow(self.model, batch, depth)
        per_level = self.flow_terms(flow, batch)
        total = flow.total
        world = batch.valid_mask  # [V, H, W], both keyframes
        consist = consistency_loss(total[0], total[1], world, world) + consistency_loss(total[1], total[0], world, world)
        terms = {"warp": per_level.pop("warp"), "consist": consist, **per_level}
        if step % self.config.render_every == 0:
            terms["render"] = self.render_term(static, batch, step, self.scene_flow(depth, flow, batch))
        terms["residual_px"] = flow.residual.detach().norm(dim=-1).mean()
        return terms

    def flow_terms(self, flow: FlowPrediction, batch: PairTensors) -> dict[str, Tensor]:
        """L_warp of R's total flow at every level (coarser levels down-weighted), and the optional
        L_flow_sup and L_search_sup, over the pixels that see the world."""
        targets = batch.images.flatten(0, 1)  # [2V, 3, H, W]
        sources = batch.images.flip(0).flatten(0, 1)  # the same cameras at the other keyframe
        world = _world(batch)
        w = self.config.weights
        levels = len(flow.residuals)
        supervise = w.flow_sup > 0
        if supervise and batch.gt_flow is None:
            raise InputError("--flow-supervision: the training pairs carry no gt_flow (synthetic pairs do)")
        if supervise:
            gt_flow, gt_valid, gt_dynamic = _flow_targets(batch)
        distil = w.search_sup > 0
        if distil:
            searched, overridden = search_targets(flow, batch)
            overridden = overridden if world is None else overridden & world
        warp = sup = search = 0.0
        for level, residual in enumerate(flow.residuals):
            total = (flow.rigid + residual).flatten(0, 1)
            warped, compared, inside = _masked_warp(sources, targets, total, world, world)
            finest = level == levels - 1
            lpips = self.perceptual if finest else None
            scale = 2 ** (levels - 1 - level)
            warp = warp + warp_loss(warped, compared, inside, lpips, w.warp_ssim, w.warp_lpips) / scale
            if supervise:
                sup = sup + supervised_flow_loss(total, gt_flow, gt_dynamic, gt_valid) / scale
            if distil:
                search = search + search_distillation_loss(total, searched, overridden) / scale
        terms = {"warp": warp}
        if supervise:
            terms["flow_sup"] = sup
        if distil:
            terms["search_sup"] = search
            terms["search_px"] = overridden.float().mean()
        return terms


def gate_loss(out, gt: Tensor, dynamic: Tensor, max_depth: float = 80.0) -> Tensor:
    """Binary cross-entropy of D's matching gate ``[2V, H, W]`` (upsampled) against where the
    matching depth alone is nearer the ground truth ``gt`` ``[2V, H, W]`` than the monocular depth
    alone (log error), over pixels with ground truth where some source is informative, moving and
    static pixels half each. It teaches the gate when to trust matching directly, also before
    the matching depth is any good (the fused loss alone then closes the gate for good)."""
    mono = torch.log(out.mono_depths[0].float().clamp(min=1e-3))
    match = torch.log(out.match_depth.float().clamp(min=1e-3))
    truth = torch.log(gt.clamp(min=1e-3))
    target = ((match - truth).abs() < (mono - truth).abs()).float().detach()
    size = gt.shape[-2:]
    informative = F.interpolate(out.matching.informative.float(), size=size, mode="nearest")[:, 0] > 0.5
    valid = (gt > 0) & (gt <= max_depth) & informative
    gate = out.gate.float().clamp(1e-4, 1 - 1e-4)
    bce = -(target * torch.log(gate) + (1 - target) * torch.log(1 - gate))
    return half_moving_half_static(bce, valid, dynamic)


def search_targets(flow: FlowPrediction, batch: PairTensors, config: MotionSearchConfig | None = None) -> tuple[Tensor, Tensor]:
    """The search's flow ``[2V, H, W, 2]`` from R's current flow (no gradient; the inference
    search, `search_motion`, at the training pairs' size) and where it is a target for R
    ``[2V, H, W]``: the search moved the flow by more than 1 px from R's, and its flows in the two
    directions agree (forward/backward). The check rejects picks that the other direction does not
    confirm, not wrong multiples of the rigid flow on flat texture (docs/training.md)."""
    with torch.no_grad():
        detached = FlowPrediction(rigid=flow.rigid, residuals=[flow.residuals[-1].detach()], warped_sources=flow.warped_sources)
        searched = search_motion(detached, batch, config or MotionSearchConfig()).searched
        consistent = torch.stack([forward_backward_consistency(searched[k], searched[1 - k]) for k in (0, 1)])
        moved = (searched - detached.total).square().sum(-1) > 1.0
    return searched.flatten(0, 1), (consistent & moved).flatten(0, 1)


def _flow_targets(batch: PairTensors) -> tuple[Tensor, Tensor, Tensor]:
    """Ground-truth flow ``[2V, H, W, 2]``, where it is usable (a surface seen at both ends, landing
    inside the other image) and the moving-object mask, for ``supervised_flow_loss``."""
    gt = batch.gt_flow.flatten(0, 1).float()
    height, width = gt.shape[1:3]
    dest = pixel_grid(height, width, dtype=gt.dtype) + gt
    valid = torch.isfinite(gt).all(-1) & (dest[..., 0] >= 0) & (dest[..., 0] <= width - 1)
    valid &= (dest[..., 1] >= 0) & (dest[..., 1] <= height - 1)
    if batch.gt_depth is not None:
        valid &= batch.gt_depth.flatten(0, 1) > 0
    if batch.valid_mask is not None:
        valid &= batch.valid_mask.repeat(2, 1, 1)
    dynamic = batch.gt_dynamic.flatten(0, 1) if batch.gt_dynamic is not None else torch.zeros_like(valid)
    return torch.nan_to_num(gt), valid, dynamic


def is_finite(loss: Tensor) -> bool:
    return bool(torch.isfinite(loss.detach()).all())
