"""Chaining D, P and R on a frame pair: shared by training (with gradients) and inference.

    depth_k        = D(I_k)                                   k = 0, 1, all V cameras at once
    rigid_{0->1}   = project(T_{1<-0} unproject(depth_0))     (ego motion and extrinsics known)
    residual_{0->1}= R(warp(I_1, rigid_{0->1}), I_0, rigid_{0->1})   and symmetrically 1 -> 0
    total          = rigid + residual
    total          = search(total, s * rigid for s in a grid)   at inference, per pixel the hypothesis
                     that matches the other keyframe best (optional, `models.lift.MotionSearchConfig`)
    scene flow     = lift(total, depth_0, depth_1)  where forward/backward-consistent and the
                     residual is above a threshold; elsewhere the Gaussian is static (zero flow)

Everything runs in the local frame of ``PairTensors`` (ego at keyframe 0). Which pixels move and
the lift to scene flow live in `models.lift`; the Gaussians from the maps in `assemble` here.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch
import torch.nn.functional as F
from torch import Tensor

from drivingscene.data.tensors import PairTensors
from drivingscene.gaussians.assembly import FootprintRule, extend_along_rays, gaussians_from_pixels, pixel_footprints
from drivingscene.gaussians.core import Gaussians
from drivingscene.geometry.camera import pixel_grid, scale_intrinsics
from drivingscene.geometry.flow import (
    backward_warp,
    rigid_flow,
)
from drivingscene.geometry.se3 import rotate_vectors
from drivingscene.models.depth import DepthOutput
from drivingscene.models.gaussian_head import PixelGaussians
from drivingscene.models.matching import ViewGeometry, neighbour_views
from drivingscene.models.model import DrivingSceneModel
from drivingscene.render.composite import SURFACE_TOLERANCE
from drivingscene.render.sh import SH_C0


def with_depth(static: StaticPrediction, depth: Tensor) -> StaticPrediction:
    """``static`` at another ``depth`` ``[2, V, H, W]``: the pixels' Gaussians slide along their rays,
    their scales follow the depth (log scales + log ratio); everything else as predicted."""
    ratio = (depth.float() / static.depth.float().clamp_min(1e-6)).clamp_min(1e-6)
    params = static.params
    log_scales = params.log_scales + ratio.log().flatten(0, 1)[..., None].to(params.log_scales.dtype)
    return replace(static, depth=depth.to(static.depth.dtype), params=replace(params, log_scales=log_scales))


def without_gaussian_head(model: DrivingSceneModel, static: StaticPrediction, batch: PairTensors) -> StaticPrediction:
    """``static`` with P's predictions replaced by its defaults (raw outputs 0: surfels one pixel
    footprint wide in the surface of the depth, the pixel's colour, opacity sigmoid(3)): the
    ablation of P (bench choices, ``head=off``)."""
    images = batch.images.flatten(0, 1).float()
    depth = static.depth.flatten(0, 1).float()
    raw = depth.new_zeros(*depth.shape, model.gaussian_head.num_out)
    params = model.gaussian_head.activate(raw, images, depth, batch.intrinsics.repeat(2, 1, 1))
    return replace(static, params=params)


@dataclass
class StaticPrediction:
    depth: Tensor  # [2, V, H, W]
    depth_output: DepthOutput  # batched over 2V images (keyframe-major)
    params: PixelGaussians  # batched over 2V images


@dataclass
class FlowPrediction:
    rigid: Tensor  # [2, V, H, W, 2]: [0] 0->1 at keyframe-0 pixels, [1] 1->0
    residuals: list[Tensor]  # per pyramid level, [2, V, H, W, 2], finest last
    warped_sources: Tensor  # [2, V, 3, H, W] the other keyframe warped by the rigid flow
    behind: Tensor | None = None  # [2, V, H, W] bool: no rigid flow there (`rigid_flows`)
    searched: Tensor | None = None  # [2, V, H, W, 2] total flow chosen by `search_motion`, if it ran

    @property
    def residual(self) -> Tensor:
        """The non-rigid part of `total`: R's finest residual, or the searched flow's."""
        return self.residuals[-1] if self.searched is None else self.searched - self.rigid

    @property
    def total(self) -> Tensor:
        return self.searched if self.searched is not None else self.rigid + self.residuals[-1]


def _resize(x: Tensor, size: tuple[int, int], mode: str) -> Tensor:
    """Resize ``[B, C, H, W]``; "area" to shrink images, "bilinear" for smooth fields."""
    if tuple(x.shape[-2:]) == tuple(size):
        return x
    kwargs = {"align_corners": False} if mode == "bilinear" else {}
    return F.interpolate(x, size=size, mode=mode, **kwargs)


def resize_flow(flow: Tensor, size: tuple[int, int]) -> Tensor:
    """Flow ``[B, 2, h, w]`` (pixels) resized bilinearly to ``size`` and its vectors rescaled to match."""
    height, width = flow.shape[-2:]
    return _resize(flow, size, "bilinear") * flow.new_tensor([size[1] / width, size[0] / height]).view(1, 2, 1, 1)


def _scaled_intrinsics(intrinsics: Tensor, src: tuple[int, int], dst: tuple[int, int]) -> Tensor:
    return scale_intrinsics(intrinsics, dst[1] / src[1], dst[0] / src[0])


def matching_sources(cam_to_ego: Tensor) -> Tensor:
    """``[2V, 3]`` batch index of each image's matching sources (`ViewGeometry`): the same camera
    at the other keyframe, then the left and right neighbours (`neighbour_views`) at the same
    keyframe; -1 where there is none (one camera: no neighbours; two: one)."""
    num_views = cam_to_ego.shape[0]
    neighbours = neighbour_views(cam_to_ego) or [(-1, -1)] * num_views
    if num_views == 2:
        neighbours = [(left, -1) for left, _ in neighbours]
    rows = [
        [(1 - k) * num_views + v] + [k * num_views + n if n >= 0 else -1 for n in neighbours[v]]
        for k in (0, 1)
        for v in range(num_views)
    ]
    return torch.tensor(rows, dtype=torch.long, device=cam_to_ego.device)


def view_geometry(batch: PairTensors, size: tuple[int, int]) -> ViewGeometry:
    """Where the pair's 2V images were taken, for D at the network input ``size``."""
    valid = None
    if batch.valid_mask is not None:
        mask = batch.valid_mask.repeat(2, 1, 1)
        if tuple(size) != tuple(batch.image_size):
            mask = F.interpolate(mask[:, None].float(), size=size, mode="area")[:, 0] > 0.5
        valid = mask
    return ViewGeometry(
        cam_to_ego=batch.cam_to_ego.repeat(2, 1, 1),
        cam_to_local=batch.cam_to_local.flatten(0, 1),
        sources=matching_sources(batch.cam_to_ego),
        valid=valid,
    )


def predict_static(model: DrivingSceneModel, batch: PairTensors, depth_images: Tensor | None = None) -> StaticPrediction:
    """D and P on both keyframes' V images.

    When the model has an ``input_size`` other than the images', the networks run on resized
    images (intrinsics scaled to match) and their outputs come back at full size: depth through
    bilinear inverse depth, P's raw outputs bilinearly, activated with the full-size image and depth.

    ``depth_images`` ``[2, V, 3, H, W]`` (training: photometrically jittered, `train.augment`), when
    given, are what D sees; P still reads ``batch.images`` (with D's features of the jittered ones).
    """
    num_views = batch.num_views
    size = batch.image_size
    net_size = model.config.input_size or size
    if depth_images is not None and (tuple(net_size) != tuple(size) or depth_images.shape != batch.images.shape):
        raise ValueError(
            f"predict_static: depth_images {list(depth_images.shape)} must match the images "
            f"{list(batch.images.shape)} at the networks' input size {list(net_size)}"
        )
    net_images, net_intrinsics, geometry = _network_inputs(batch, net_size)
    if tuple(net_size) == tuple(size):
        channels_last = None if depth_images is None else depth_images.flatten(0, 1).contiguous(memory_format=torch.channels_last)
        depth_out, params = model.static(net_images, net_intrinsics, geometry, channels_last)
        depth = depth_out.depth
    else:
        depth_out, raw = model.static_raw(net_images, net_intrinsics, geometry)
        depth = _full_size_depth(depth_out.depth, size)
        # channels-last in, channels-last out: the upsampled [B, H, W, C] view is then contiguous
        raw = raw.permute(0, 3, 1, 2).contiguous(memory_format=torch.channels_last)
        raw = _resize(raw, size, "bilinear").permute(0, 2, 3, 1)
        params = model.gaussian_head.activate(raw, batch.images.flatten(0, 1), depth, batch.intrinsics.repeat(2, 1, 1))
    return StaticPrediction(depth=depth.unflatten(0, (2, num_views)), depth_output=depth_out, params=params)


def predict_depth(model: DrivingSceneModel, batch: PairTensors) -> Tensor:
    """D alone on both keyframes' V images: ``[2, V, H, W]`` z-depth, what `predict_static` returns
    as ``depth`` without running P (test-time adaptation trains D on depth losses only)."""
    size = batch.image_size
    net_images, net_intrinsics, geometry = _network_inputs(batch, model.config.input_size or size)
    depth = model.depth_net(net_images, net_intrinsics, geometry).depth
    return _full_size_depth(depth, size).unflatten(0, (2, batch.num_views))


def _network_inputs(batch: PairTensors, net_size: tuple[int, int]) -> tuple[Tensor, Tensor, ViewGeometry]:
    """The 2V images (channels-last) and intrinsics at the networks' input size, and D's geometry."""
    size = batch.image_size
    intrinsics = batch.intrinsics.repeat(2, 1, 1)
    if tuple(net_size) == tuple(size):
        images = batch.images.flatten(0, 1)
    else:
        images = batch.resized_images(net_size).flatten(0, 1)
        intrinsics = _scaled_intrinsics(intrinsics, size, net_size)
    return images.contiguous(memory_format=torch.channels_last), intrinsics, view_geometry(batch, net_size)


def _full_size_depth(depth: Tensor, size: tuple[int, int]) -> Tensor:
    """D's depth ``[B, h, w]`` at the images' ``size`` (bilinear in inverse depth; as it is at that size)."""
    if tuple(depth.shape[-2:]) == tuple(size):
        return depth
    return 1.0 / _resize(1.0 / depth.float()[:, None], size, "bilinear")[:, 0]


def bound_flow(flow: Tensor) -> Tensor:
    """Clamp flow ``[..., H, W, 2]`` so that its destinations stay within one image size of the image.

    Points that land behind the destination camera project to arbitrarily far (up to 1e6 px)
    coordinates; such a flow only says "leaves the view", and unbounded it would swamp R's input
    and every pooled flow error. Destinations are clamped to [-W, 2W - 1] x [-H, 2H - 1].
    """
    height, width = flow.shape[-3:-1]
    grid = pixel_grid(height, width, dtype=flow.dtype, device=flow.device)
    lo = flow.new_tensor([-width, -height])
    hi = flow.new_tensor([2 * width - 1, 2 * height - 1])
    return torch.minimum(torch.maximum(grid + flow, lo), hi) - grid


# Nearer than this (metres, in front of the destination camera) a static point has no usable rigid
# flow: it would pass behind the camera (or project arbitrarily far off the image).
NEAR_Z = 0.5


def rigid_flows(depth: Tensor, batch: PairTensors) -> Tensor:
    """``[2, V, H, W, 2]`` rigid flow 0->1 from depth_0 and 1->0 from depth_1, bounded (`bound_flow`).

    Where a static world would carry the point behind the other keyframe's camera (nearer than
    ``NEAR_Z``), the rigid flow is 0: a surface there that is still seen at the other keyframe
    moves with the ego (a car following close behind, or keeping pace ahead), and one that is not
    seen has no flow to find. R's residual starts from there, and the Gaussian stays static
    unless R moves it.
    """
    return rigid_flows_and_behind(depth, batch)[0]


def rigid_flows_and_behind(depth: Tensor, batch: PairTensors) -> tuple[Tensor, Tensor]:
    """`rigid_flows` and the mask ``[2, V, H, W]`` of pixels it set to 0 (behind the other camera)."""
    c2l = batch.cam_to_local
    f01, z01 = rigid_flow(depth[0], batch.intrinsics, c2l[0], c2l[1])
    f10, z10 = rigid_flow(depth[1], batch.intrinsics, c2l[1], c2l[0])
    flow = bound_flow(torch.stack([f01, f10]))
    behind = torch.stack([z01, z10]) < NEAR_Z
    return torch.where(behind[..., None], torch.zeros_like(flow), flow), behind


def predict_flow(
    model: DrivingSceneModel, batch: PairTensors, depth: Tensor, finest_level: int = 0, all_levels: bool = True
) -> FlowPrediction:
    """Rigid flow from ``depth`` ``[2, V, H, W]`` and R's residual, both directions.

    The rigid flow is always computed at full size; R runs at the model's ``input_size`` on the
    resized images and rigid flow, and its residual is resized (and rescaled) back. R refines
    down to its pyramid level ``finest_level`` (0: all levels); ``all_levels=False`` keeps only the
    finest computed level's residual (inference: the training losses use every level).
    """
    size = batch.image_size
    net_size = tuple(model.config.input_size or size)
    rigid, behind = rigid_flows_and_behind(depth, batch)
    images = batch.resized_images(net_size)
    targets = images.flatten(0, 1)  # [2V, 3, h, w]
    sources = images.flip(0).flatten(0, 1)  # the other keyframe
    rigid_chw = rigid.flatten(0, 1).permute(0, 3, 1, 2)
    if net_size != tuple(size):
        to_net = rigid_chw.new_tensor([net_size[1] / size[1], net_size[0] / size[0]]).view(1, 2, 1, 1)
        rigid_chw = resize_flow(rigid_chw, net_size)
    warped, _ = backward_warp(sources, rigid_chw.permute(0, 2, 3, 1))
    slots = model.camera_slots(batch.cam_to_ego).repeat(2)
    residuals = model.residual_flow(warped, targets, rigid_chw, slots, sources, finest_level, all_levels)
    if net_size != tuple(size):
        residuals = [_resize(r.float(), size, "bilinear") / to_net for r in residuals]
    residuals = [r.float().permute(0, 2, 3, 1).unflatten(0, (2, batch.num_views)) for r in residuals]
    warped = warped.unflatten(0, (2, batch.num_views))
    return FlowPrediction(rigid=rigid, residuals=residuals, warped_sources=warped, behind=behind)


def assemble(
    static: StaticPrediction,
    batch: PairTensors,
    sky: Tensor,  # [2, V, H, W] bool
    scene_flow: Tensor | None = None,  # [2, V, H, W, 3]
    keyframes: tuple[int, ...] = (0, 1),
    local_to_world: Tensor | None = None,  # [4, 4]: build them in the world frame directly
    fit_colors: int = 0,
    footprints: FootprintRule = FootprintRule(),
    surface_tolerance: float = SURFACE_TOLERANCE,
    ray_extent: float = 0.0,
) -> Gaussians:
    """Gaussians of the requested keyframes in the local frame, or the world frame with
    ``local_to_world`` (one pass, not a second transform of every Gaussian); sky pixels excluded.
    ``fit_colors`` > 0: that many iterations of the colour solve (`render.color_solve`) that makes
    each input image's own Gaussians re-render it (inference; training leaves the colours to P).
    ``footprints``: the footprint rule applied to P's scales (`gaussians.assembly`);
    ``surface_tolerance``: the own layer's rule the solve fits for (the layered blends');
    ``ray_extent`` > 0: each Gaussian extended along its view ray (`gaussians.assembly.extend_along_rays`;
    inference: not differentiable)."""
    num_views = batch.num_views
    p = static.params
    cams = batch.cam_to_local
    if local_to_world is not None:
        cams = (local_to_world.double() @ cams.double()).to(cams.dtype)
        if scene_flow is not None:
            scene_flow = rotate_vectors(local_to_world[:3, :3].to(scene_flow.dtype), scene_flow)
    # The requested keyframes' views as one batch of len(keyframes) * V views (one pass).
    views = torch.cat([torch.arange(k * num_views, (k + 1) * num_views) for k in keyframes]).to(sky.device)
    first, count = keyframes[0] * num_views, len(keyframes) * num_views
    contiguous = list(keyframes) == list(range(keyframes[0], keyframes[0] + len(keyframes)))

    def per_view(x: Tensor) -> Tensor:  # [2V, ...] (keyframe-major) -> the requested views
        return x[first : first + count] if contiguous else x[views]

    depth = per_view(static.depth.flatten(0, 1))
    intrinsics = batch.intrinsics.repeat(len(keyframes), 1, 1)
    quats, valid, sh = per_view(p.quats), ~per_view(sky.flatten(0, 1)), per_view(p.sh)
    log_scales = pixel_footprints(depth.detach(), intrinsics, quats, per_view(p.log_scales), footprints)
    if fit_colors > 0:
        sh = _fitted_sh(
            depth, intrinsics, quats, log_scales, per_view(p.opacity_logits), sh, per_view(batch.images.flatten(0, 1)), valid,
            fit_colors, surface_tolerance,
        )  # fmt: skip
    if ray_extent > 0:  # after the solve: the own views do not see it
        quats, log_scales = extend_along_rays(depth, intrinsics, quats, log_scales, ray_extent)
    return gaussians_from_pixels(
        depth,
        intrinsics,
        per_view(cams.flatten(0, 1)),
        sh,
        keyframe=views // num_views,
        camera_ids=views % num_views,
        log_scales=log_scales,
        quats=quats,
        opacity_logits=per_view(p.opacity_logits),
        flows=None if scene_flow is None else per_view(scene_flow.flatten(0, 1)),
        valid=valid,
        footprints=None,
    )


def _fitted_sh(
    depth, intrinsics, quats, log_scales, opacity_logits, sh, images, valid, iterations: int, tolerance: float
) -> Tensor:
    """``sh`` ``[I, H, W, K, 3]`` with the DC colour solved by `solve_pixel_colors` (images ``[I, 3, H, W]``)."""
    from drivingscene.render.color_solve import solve_pixel_colors

    start = SH_C0 * sh[..., 0, :].float() + 0.5  # the view-independent colour, unclamped
    solved = solve_pixel_colors(
        depth.detach().float(),
        intrinsics,
        quats.detach(),
        log_scales.detach(),
        torch.sigmoid(opacity_logits.detach().float()),
        start.detach().clamp(min=0.0),
        images.permute(0, 2, 3, 1).float(),
        valid,
        iterations,
        surface_tolerance=tolerance,
    )
    change = torch.where(solved > 0, solved - start, (-start).clamp(max=0.0))
    out = sh.clone()
    out[..., 0, :] = sh[..., 0, :] + (change / SH_C0).to(sh.dtype)
    return out
