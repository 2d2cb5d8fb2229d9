"""From optical flow to the motion the Gaussians make, at inference and in training: which pixels
the static world explains (parallax along the epipolar lines, `explain_by_parallax`), the search
for a better flow along the rigid one (`search_motion`, `MotionSearchConfig`), and the lift of
what is left to scene flow (`lift_scene_flow`, `LiftConfig`). `models.pipeline` chains the
networks that predict the flows; this module decides what of them moves.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch
import torch.nn.functional as F
from torch import Tensor

from drivingscene import kernels
from drivingscene.data.tensors import PairTensors
from drivingscene.geometry.camera import pixel_grid
from drivingscene.geometry.flow import (
    FB_ALPHA,
    FB_BETA,
    forward_backward_consistency,
    forward_backward_consistency_at,
    inside_image,
    sample_bilinear,
    vector_length,
)
from drivingscene.geometry.flow_search import flow_from_choice, luma, median_of_choice, search_along_rigid
from drivingscene.geometry.scene_flow import scene_flow_at_pixels, scene_flow_from_optical_flow
from drivingscene.models.pipeline import NEAR_Z, FlowPrediction, resize_flow

EPIPOLAR_DEPTHS = ("triangulated", "unmatched", "keep")


@dataclass(frozen=True)
class LiftConfig:
    # Pixels whose depth, brought to the reference focal length, exceeds this are sky: background,
    # no Gaussian. (Depth scales with fx / W, so the threshold does too; see models/depth.py.)
    sky_depth: float = 100.0
    # Residual flow below this many pixels *of the networks' input size* is treated as static (R
    # runs there, so its precision is set there): 1 px at 96x176 is 1.8 px at 176x320. Chosen on
    # validation pairs at 176x320 (`data/val176`) among 1, 1.8, 3, 5, 8 px there.
    dynamic_threshold_px: float = 1.0
    # Optionally, a candidate pixel moves only if the other keyframe, sampled along the total flow,
    # matches it better than sampled along the rigid flow: a residual that does not explain the
    # images is not trusted (needs the rigid flow). Off by default: on validation pairs it raised
    # all-pixel PSNR but lowered the moving-pixel gain, and costs ~45 ms at 176x320 (results-notes).
    photometric_check: bool = False
    # Pixels without a rigid flow (a static world would carry them behind the other camera;
    # `rigid_flows`) are candidates whatever their residual: still seen at the other keyframe,
    # they move with the ego.
    behind_candidates: bool = True
    # Dynamic regions (8-connected, per image) smaller than this many pixels *of the networks'
    # input size* stay static: moving objects are blobs, isolated moving pixels are noise of the
    # search or of R where the image is flat or the depth is off. 0: keep every dynamic pixel.
    min_dynamic_region: int = 0
    # Parallax before motion: a candidate pixel whose total flow stays within ``epipolar_px`` (at the
    # networks' input size) of its epipolar line in the other keyframe, and whose triangulated depth
    # lies within [``epipolar_near``, ``epipolar_far``] m, is explained by a static surface at that
    # depth (`explain_by_parallax`): it stays static and takes the triangulated depth. Motion along
    # the epipolar line and a depth error cannot be told apart from two frames; for the keyframes
    # and every time between them (pure translation) both project to the same pixels, so the static
    # answer renders the same and moves nothing that does not need to move. Off: R's and the search's
    # flow decide alone. On, with 4 px of parallax, chosen on validation pairs (data/val176 and
    # data/val176rand, `drivingscene bench choices`, docs/choices.md): 12-15 % dynamic Gaussians
    # became 3 %, depth and the in-between frame as they were (within 0.006 AbsRel and 0.15 dB).
    epipolar_static: bool = True
    epipolar_px: float = 1.0
    epipolar_near: float = 1.0
    epipolar_far: float = 80.0
    # It takes the triangulated depth only where that is well determined: the point at least this
    # many pixels (at the networks' input size) from where it would be at infinite depth, so that a
    # pixel of flow error is a small relative depth error (1 / parallax); elsewhere it keeps the
    # network's depth (and is still static: with little parallax, depth moves it little).
    epipolar_min_parallax: float = 4.0
    # ... and where the image can tell positions along the line apart (the aperture problem): the
    # mean |luma derivative along the epipolar direction| over a 5x5 window (at the networks' input
    # size) at least this (luma in [0, 1] per pixel). 0: no test.
    epipolar_min_texture: float = 0.0
    # Which pixels are tested: "dynamic" (those the lift calls moving) or "residual" (also every
    # pixel whose residual exceeds the threshold, which then may take a triangulated depth).
    epipolar_candidates: str = "dynamic"
    # Which explained pixels take their triangulated depth: "triangulated" (every well-determined
    # one), "unmatched" (not those whose depth the matching at inference already triangulated from
    # its own flow, `methods/matched_depth.py`: they keep it), or "keep" (none: explained pixels only
    # become static).
    epipolar_depth: str = "triangulated"

    def __post_init__(self):
        if self.epipolar_depth not in EPIPOLAR_DEPTHS:
            raise ValueError(f"LiftConfig.epipolar_depth: expected one of {EPIPOLAR_DEPTHS}, found {self.epipolar_depth!r}")


def explain_by_parallax(
    depth: Tensor,  # [2, V, H, W] z-depth
    flow: FlowPrediction,
    candidates: Tensor,  # [2, V, H, W] bool: the pixels to test (`lift_scene_flow`'s dynamic ones)
    batch: PairTensors,
    config: LiftConfig,
    net_width: int | None = None,
    fixed: Tensor | None = None,  # [2, V, H, W] bool: pixels whose depth stays as it is
) -> tuple[Tensor, FlowPrediction, Tensor]:
    """Moving pixels that a static surface at another depth explains (`LiftConfig.epipolar_static`).

    For each candidate whose total flow ends inside the other image, the flow's end point is
    compared with the pixel's epipolar line in the same camera at the other keyframe (capture
    poses from the batch) and triangulated along the pixel's ray (least squares over both image
    axes). Explained: within ``epipolar_px`` of the line, triangulated in front of both cameras
    within [``epipolar_near``, ``epipolar_far``], with at least ``epipolar_min_parallax``.
    Returns the depth with the explained pixels at their triangulated depth (except those in
    ``fixed``, which keep theirs), the flow with their rigid flow set to the total flow (residual
    0; the total flow unchanged), and the ``[2, V, H, W]`` mask of explained pixels. The geometry
    is `epipolar_geometry`'s.
    """
    total, rigid = flow.total, flow.rigid
    width = depth.shape[-1]
    scale = width / net_width if net_width else 1.0
    c2l = batch.cam_to_local.float()
    depths, explained_all, determined_all = [], [], []
    for k in (0, 1):
        o = 1 - k
        rel = torch.linalg.inv(c2l[o]) @ c2l[k]  # [V, 4, 4] camera at k -> the same camera at o
        z, off_line, parallax, valid = epipolar_geometry(total[k].float(), batch.intrinsics.float(), rel)
        explained, determined = epipolar_tests(z, off_line, vector_length(parallax), valid, candidates[k], config, scale)
        if config.epipolar_min_texture > 0 and determined.any():
            determined &= texture_along(batch.images[k].float(), parallax, scale) >= config.epipolar_min_texture
        if fixed is not None:
            determined &= ~fixed[k]
        depths.append(torch.where(determined, z.to(depth.dtype), depth[k]))
        explained_all.append(explained)
        determined_all.append(determined)
    explained, determined = torch.stack(explained_all), torch.stack(determined_all)
    new_rigid = torch.where(determined[..., None], total, rigid)
    return torch.stack(depths), replace(flow, rigid=new_rigid, searched=total), explained


def epipolar_tests(
    z: Tensor, off_line: Tensor, parallax_px: Tensor, valid: Tensor, candidates: Tensor, config: LiftConfig, scale: float = 1.0
) -> tuple[Tensor, Tensor]:
    """`explain_by_parallax`'s tests on `epipolar_geometry`'s output: explained (a candidate,
    valid, triangulated within [``epipolar_near``, ``epipolar_far``] and within ``epipolar_px``
    of its epipolar line) and determined (explained with at least ``epipolar_min_parallax``;
    without the texture test). ``parallax_px``: the length of the parallax ``[V, H, W]``
    (`vector_length`). ``scale``: image pixels per pixel of the thresholds."""
    ok = valid & (z >= config.epipolar_near) & (z <= config.epipolar_far)
    explained = candidates & ok & (off_line <= config.epipolar_px * scale)
    # The depth is only taken where it is well determined; elsewhere the pixel is static at the
    # network's depth (which then moves it by less than the little parallax there is).
    determined = explained & (parallax_px >= config.epipolar_min_parallax * scale)
    return explained, determined


def _rays(intrinsics: Tensor, rel: Tensor, height: int, width: int) -> tuple[Tensor, Tensor]:
    """``K^-1`` ``[V, 3, 3]`` and each pixel's ray in the other camera's axes ``[V, H, W, 3]``
    (z = 1 in its own: the ray scaled by z-depth)."""
    k_inv = torch.linalg.inv(intrinsics)
    grid = pixel_grid(height, width, device=intrinsics.device, dtype=torch.float32)  # [H, W, 2] (u, v)
    pixels_h = torch.cat([grid, torch.ones_like(grid[..., :1])], -1)  # [H, W, 3]
    rays = torch.einsum("vij,hwj->vhwi", k_inv, pixels_h)
    return k_inv, torch.einsum("vij,vhwj->vhwi", rel[:, :3, :3], rays)


def epipolar_geometry(
    flow: Tensor,  # [V, H, W, 2] one keyframe's flow to the same cameras at the other keyframe
    intrinsics: Tensor,  # [V, 3, 3]
    rel: Tensor,  # [V, 4, 4] each camera at this keyframe -> the same camera at the other
    backend: str = "auto",
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Each pixel's flow end point against its epipolar line (float32): the depth ``z``
    ``[V, H, W]`` along the pixel's ray whose image in the other camera is nearest the end point
    (least squares over both image axes), that image's distance from the end point (off the
    line, pixels, ``[V, H, W]``), its offset from the image of the ray's point at infinite depth
    (the parallax, pixels, ``[V, H, W, 2]``: along the line, away from infinity), and ``valid``
    ``[V, H, W]``: the point in front of the other camera (z-depth there
    above ``NEAR_Z``), the ray pointing forward there, the end point inside the image and ``z``
    finite. The compiled op (`drivingscene.kernels.epipolar_parallax`) computes the same in one pass
    per pixel on the CPU; ``backend``: "auto", "cpp" or "torch" (`drivingscene.kernels.available`)."""
    num_views, height, width = flow.shape[:3]
    if kernels.available(kernels.epipolar_parallax, backend, flow, intrinsics, rel):
        return kernels.epipolar_parallax(flow, intrinsics, torch.linalg.inv(intrinsics), rel, NEAR_Z)
    k_inv, a = _rays(intrinsics, rel, height, width)
    grid = pixel_grid(height, width, device=flow.device, dtype=torch.float32)
    target = torch.cat([grid + flow, torch.ones_like(flow[..., :1])], -1)
    x = torch.einsum("vij,vhwj->vhwi", k_inv, target)  # normalised coordinates of the end point
    t = rel[:, None, None, :3, 3]
    # lambda * (a_xy - x_xy a_z) = x_xy t_z - t_xy  (projection of lambda * a + t onto x)
    coef = a[..., :2] - x[..., :2] * a[..., 2:3]
    rhs = x[..., :2] * t[..., 2:3] - t[..., :2]
    z = (coef * rhs).sum(-1) / coef.square().sum(-1).clamp_min(1e-12)
    point = z[..., None] * a + t
    proj = torch.einsum("vij,vhwj->vhwi", intrinsics, point)
    proj = proj[..., :2] / proj[..., 2:3].clamp_min(1e-6)
    off_line = vector_length(proj - target[..., :2])
    # Parallax: how far along the line the point is from its image at infinite depth. The
    # triangulated depth's relative error is about the flow's error over it (pixels).
    at_infinity = torch.einsum("vij,vhwj->vhwi", intrinsics, a)
    at_infinity = at_infinity[..., :2] / at_infinity[..., 2:3].clamp_min(1e-6)
    parallax = proj - at_infinity
    inside = (target[..., 0] >= 0) & (target[..., 0] <= width - 1) & (target[..., 1] >= 0) & (target[..., 1] <= height - 1)
    valid = (point[..., 2] > NEAR_Z) & (a[..., 2] > 0) & inside & torch.isfinite(z)
    return z, off_line, parallax, valid


def texture_along(images: Tensor, direction: Tensor, scale: float) -> Tensor:
    """``[V, H, W]`` mean |luma derivative along ``direction`` ``[V, H, W, 2]``| over a 5x5
    window at the networks' input size (``scale`` image pixels per network pixel), per network
    pixel. Central differences and the window's mean with replicated borders (what kornia's
    ``spatial_gradient(mode="diff")`` and ``box_blur`` compute, a few times faster)."""
    import cv2

    gray = F.pad(luma(images), (1, 1, 1, 1), mode="replicate")  # [V, 1, H + 2, W + 2]
    du = 0.5 * (gray[:, 0, 1:-1, 2:] - gray[:, 0, 1:-1, :-2])
    dv = 0.5 * (gray[:, 0, 2:, 1:-1] - gray[:, 0, :-2, 1:-1])
    norm = vector_length(direction).clamp_min(1e-12)
    along = ((du * direction[..., 0] + dv * direction[..., 1]) / norm).abs() * scale
    size = max(1, int(round(5 * scale))) | 1
    if along.device.type != "cpu" or along.dtype != torch.float32:
        pad = size // 2
        return F.avg_pool2d(F.pad(along[:, None], (pad, pad, pad, pad), mode="replicate"), size, stride=1)[:, 0]
    out = along.numpy().copy()
    for i in range(len(out)):  # OpenCV's box filter: running sums, a fraction of avg_pool2d's time
        out[i] = cv2.blur(out[i], (size, size), borderType=cv2.BORDER_REPLICATE)
    return torch.from_numpy(out)


def drop_small_regions(mask: Tensor, min_pixels: float) -> Tensor:
    """``mask`` ``[..., H, W]`` bool without its 8-connected regions of fewer than ``min_pixels`` pixels."""
    import cv2
    import numpy as np

    if min_pixels <= 1:
        return mask
    flat = mask.reshape(-1, *mask.shape[-2:]).cpu().numpy().astype(np.uint8)
    out = np.zeros_like(flat, dtype=bool)
    for i, image in enumerate(flat):
        count, labels, stats, _ = cv2.connectedComponentsWithStats(image, connectivity=8)
        keep = stats[:, cv2.CC_STAT_AREA] >= min_pixels
        keep[0] = False  # the background label
        out[i] = keep[labels]
    return torch.from_numpy(out).to(mask.device).reshape(mask.shape)


@dataclass(frozen=True)
class MotionSearchConfig:
    """The search along the rigid flow that refines R's flow at inference (`search_motion`).

    Each pixel keeps, among ``s * rigid`` for s from ``scale_min`` to ``scale_max`` in steps of
    ``scale_step`` and R's total flow, the flow along which the other keyframe matches it best
    (geometry/flow_search.py). With the ego at 8 m/s, s = -0.5 is a car pulling away at 1.5 times
    its speed and s = 3 an oncoming one at twice it. Chosen on validation pairs (`data/val176`,
    never the test pairs); docs/results-notes.md gives the figures.
    """

    scale_min: float = -0.5
    scale_max: float = 3.0
    scale_step: float = 0.1
    # Odd box window (pixels at the networks' input size) over which the photometric cost is averaged.
    window: int = 7
    # Subtracted from the cost (mean absolute luma difference in [0, 1]) of R's flow, so that near
    # ties go to R, and of s = 1, so that a pixel leaves the static world only when another
    # hypothesis matches clearly better.
    network_bonus: float = 0.002
    static_bonus: float = 0.01
    # Odd window (pixels at the networks' input size) of the median filter over the chosen scales
    # (`median_of_choice`); 1: none.
    median_window: int = 9
    # False: search among the scaled rigid flows only (diagnostic: the search without R).
    use_network: bool = True
    # R's pyramid level whose flow is the proposal: R stops refining there (0: its finest level,
    # at 1/2 of its input size; 1: at 1/4, which skips the level that takes about half of R's
    # time). On validation pairs level 1 scored within 0.005 dB of level 0 (docs/search.md).
    proposal_level: int = 1
    # Where the static hypothesis (s = 1) leads outside the other image, the other keyframe cannot
    # say whether the pixel is static (a sample outside costs as much as the worst match), so any
    # hypothesis that lands inside won there: on side cameras 30-50 % of static surfaces, those
    # leaving the view, took a random s (issue 21). True: a scaled-rigid pick there falls back to
    # s = 1 (R's flow, when it wins, is kept): without evidence the world stays static. Chosen on
    # 20 validation pairs (docs/choices-unseen.md): the in-between frame +0.22 dB on data/val176
    # and +0.05 dB on data/val176rand, moving pixels within 0.05 dB, depth AbsRel as good or
    # better, dynamic Gaussians 3.1 % -> 0.9 % and 2.5 % -> 1.2 %. False: the search decides there too.
    unseen_static: bool = True
    # ... only where R's own flow moves the pixel less than this many pixels (at the networks' input
    # size) away from the rigid flow: where R sees motion, that is evidence, and the search's pick
    # stands (a car leaving the view). 0: every such pick falls back to s = 1.
    unseen_residual_px: float = 0.0

    def __post_init__(self):
        if not (self.scale_step > 0 and self.scale_min <= 1.0 <= self.scale_max):
            raise ValueError(
                "MotionSearchConfig: expected scale_step > 0 and scale_min <= 1 <= scale_max, found "
                f"{self.scale_step}, {self.scale_min}, {self.scale_max}"
            )
        if self.proposal_level < 0:
            raise ValueError(f"MotionSearchConfig.proposal_level: expected >= 0, found {self.proposal_level}")
        for name in ("window", "median_window"):
            if getattr(self, name) < 1 or getattr(self, name) % 2 == 0:
                raise ValueError(f"MotionSearchConfig.{name}: expected an odd number >= 1, found {getattr(self, name)}")

    def scales(self) -> Tensor:
        """The grid of s, with 1 on it exactly (the static hypothesis)."""
        below = torch.arange(round((1.0 - self.scale_min) / self.scale_step), 0, -1, dtype=torch.float64)
        above = torch.arange(0, round((self.scale_max - 1.0) / self.scale_step) + 1, dtype=torch.float64)
        return (1.0 + torch.cat([-below, above]) * self.scale_step).float()


def sky_distance(intrinsics: Tensor, width: int, ref_focal: float, config: LiftConfig) -> Tensor:
    """``[V]`` metres: the depth beyond which a camera's pixels are treated as sky (``config.sky_depth``
    at the reference focal length, in proportion to each camera's focal length over its width)."""
    return config.sky_depth * (intrinsics[:, 0, 0] / width) / ref_focal


def sky_mask(depth: Tensor, intrinsics: Tensor, ref_focal: float, config: LiftConfig) -> Tensor:
    """``[..., V, H, W]`` bool: pixels treated as sky, for depth ``[..., V, H, W]``."""
    return depth > sky_distance(intrinsics, depth.shape[-1], ref_focal, config)[:, None, None]


def search_motion(
    flow: FlowPrediction, batch: PairTensors, config: MotionSearchConfig, net_size: tuple[int, int] | None = None
) -> FlowPrediction:
    """``flow`` with ``searched`` set: per pixel, R's total flow or a multiple of the rigid flow,
    whichever the other keyframe matches best (`MotionSearchConfig`). The search runs on luma at
    ``net_size`` (R's input size; default the images') and its choice is applied at full size."""
    size = tuple(batch.image_size)
    net_size = tuple(net_size or size)
    small = batch.resized_images(net_size)
    images = luma(small.flatten(0, 1))  # [2V, 1, h, w], keyframe-major
    others = luma(small.flip(0).flatten(0, 1))
    rigid, total = flow.rigid.flatten(0, 1), flow.total.flatten(0, 1)
    rigid_net, total_net = rigid, total
    if net_size != size:
        rigid_net, total_net = (resize_flow(f.permute(0, 3, 1, 2), net_size).permute(0, 2, 3, 1) for f in (rigid, total))
    scales = config.scales()
    proposal = total_net if config.use_network else None
    choice = search_along_rigid(
        images, others, rigid_net, scales, config.window, proposal, config.network_bonus, config.static_bonus
    )
    if config.unseen_static:
        grid = pixel_grid(*net_size, device=rigid_net.device, dtype=rigid_net.dtype)
        unseen = ~inside_image(grid + rigid_net, *net_size) & (choice < len(scales))
        if config.unseen_residual_px > 0:
            unseen &= vector_length(total_net - rigid_net) < config.unseen_residual_px
        choice = torch.where(unseen, int((scales - 1.0).abs().argmin()), choice)  # scales() has 1 exactly
    choice = median_of_choice(choice, scales, config.median_window)
    if net_size != size:
        choice = F.interpolate(choice[:, None].float(), size=size, mode="nearest")[:, 0].long()
    searched = flow_from_choice(choice, scales, rigid, total if config.use_network else None)
    return replace(flow, searched=searched.unflatten(0, (2, batch.num_views)))


# Without the compiled kernel: above this share of candidate pixels the torch lift computes every
# pixel (dense) instead of gathering the candidates: the same result, and about twice as fast at ~60 %.
DENSE_LIFT_SHARE = 0.3


def lift_scene_flow(
    depth: Tensor,
    total: Tensor,
    residual: Tensor,
    sky: Tensor,
    batch: PairTensors,
    config: LiftConfig,
    net_width: int | None = None,  # the networks' input width when it differs from the image's
    rigid: Tensor | None = None,  # [2, V, H, W, 2]: enables config.photometric_check
    behind: Tensor | None = None,  # [2, V, H, W] bool: candidates whatever their residual (no rigid flow)
) -> tuple[Tensor, Tensor]:
    """World (local-frame) displacement ``[2, V, H, W, 3]`` and dynamic mask ``[2, V, H, W]``.

    A pixel moves only where its residual exceeds the threshold, its flow is forward/backward
    consistent, both depths are valid and (with ``rigid`` and ``config.photometric_check``) the
    total flow matches the other keyframe better than the rigid flow does; every other pixel falls
    back to static. Only the candidate pixels (residual above the threshold, or ``behind``, where
    the rigid flow is 0 because a static world would carry the point behind the other camera, so
    that a small residual means "moves with the ego"; not sky) are lifted: a few percent of the image.
    """
    c2l = batch.cam_to_local
    num_views, height, width = depth.shape[1:]
    threshold = config.dynamic_threshold_px * (width / net_width if net_width else 1.0)
    check = rigid is not None and config.photometric_check
    if check:  # both keyframes box-filtered once (each is target once and source once), channels last
        smooth = F.avg_pool2d(F.pad(batch.images.flatten(0, 1), (1, 1, 1, 1), mode="replicate"), 3, stride=1)
        smooth = smooth.unflatten(0, (2, num_views)).permute(0, 1, 3, 4, 2)
    flows, masks = [], []
    for k in (0, 1):
        o = 1 - k
        moving = residual[k].detach().square().sum(-1) > threshold**2
        if behind is not None and config.behind_candidates:
            moving |= behind[k]
        moving &= ~sky[k]
        # the same result in one compiled pass over every pixel (`drivingscene.kernels.lift_dense`,
        # inference only): faster than gathering the candidates at any share measured (12-60 %)
        if not check and kernels.available(kernels.lift_dense, "auto", depth[k], depth[o], total[k], total[o], c2l):
            sf, dynamic = kernels.lift_dense(
                depth[k], depth[o], total[k], total[o], moving, batch.intrinsics, c2l[k], c2l[o], FB_ALPHA, FB_BETA
            )
            flows.append(sf)
            masks.append(dynamic)
            continue
        if not check and moving.float().mean() > DENSE_LIFT_SHARE:  # cheaper at every pixel, same result
            sf, valid = scene_flow_from_optical_flow(depth[k], depth[o], total[k], batch.intrinsics, c2l[k], c2l[o])
            dynamic = moving & valid & forward_backward_consistency(total[k].detach(), total[o].detach())
            flows.append(torch.where(dynamic[..., None], sf, torch.zeros_like(sf)))
            masks.append(dynamic)
            continue
        index, row, col = moving.nonzero(as_tuple=True)
        pixels = torch.stack([col, row], -1)
        sf, valid = scene_flow_at_pixels(depth[k], depth[o], total[k], batch.intrinsics, c2l[k], c2l[o], index, pixels)
        dynamic = valid & forward_backward_consistency_at(total[k], total[o], index, pixels)
        if check:
            dynamic &= total_flow_matches_better(smooth[k], smooth[o], total[k].detach(), rigid[k], index, pixels)
        sf = torch.where(dynamic[:, None], sf, torch.zeros_like(sf))
        flows.append(total.new_zeros(num_views, height, width, 3).index_put((index, row, col), sf))
        masks.append(torch.zeros_like(moving).index_put((index, row, col), dynamic))
    flows, masks = torch.stack(flows), torch.stack(masks)
    if config.min_dynamic_region > 0:
        scale = (width / net_width) ** 2 if net_width else 1.0
        masks = drop_small_regions(masks, config.min_dynamic_region * scale)
        flows = torch.where(masks[..., None], flows, torch.zeros_like(flows))
    return flows, masks


def total_flow_matches_better(
    target: Tensor,  # [V, H, W, 3] channels last
    source: Tensor,  # [V, H, W, 3] the other keyframe
    total: Tensor,  # [V, H, W, 2]
    rigid: Tensor,  # [V, H, W, 2]
    index: Tensor,  # [P] camera of each pixel
    pixels: Tensor,  # [P, 2] integer (u, v)
) -> Tensor:
    """``[P]`` bool: pixels where ``source`` matches ``target`` better along the ``total`` flow
    than along the ``rigid`` flow (mean absolute colour difference; a sample outside the image is
    a mismatch). Evaluated at the given pixels only; `lift_scene_flow` passes 3x3-box-filtered
    images, so that single noisy pixels do not decide."""
    height, width = target.shape[1:3]
    here = target[index, pixels[:, 1], pixels[:, 0]]
    errors, inside = [], []
    for flow in (total, rigid):
        uv = pixels.to(flow.dtype) + flow[index, pixels[:, 1], pixels[:, 0]]
        errors.append((sample_bilinear(source, index, uv) - here).abs().mean(-1))
        inside.append(inside_image(uv, height, width))
    return inside[0] & (~inside[1] | (errors[0] < errors[1]))
