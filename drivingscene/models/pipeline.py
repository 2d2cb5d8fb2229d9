"""Chaining D, P and R on a frame pair: shared by training (with gradients) and inference.

    depth_k        = D(I_k)                                   k = 0, 1, all V cameras at once
    rigid_{0->1}   = project(T_{1<-0} unproject(depth_0))     (ego motion and extrinsics known)
    residual_{0->1}= R(warp(I_1, rigid_{0->1}), I_0, rigid_{0->1})   and symmetrically 1 -> 0
    total          = rigid + residual
    total          = search(total, s * rigid for s in a grid)   at inference, per pixel the hypothesis
                     that matches the other keyframe best (optional, `MotionSearchConfig`)
    scene flow     = lift(total, depth_0, depth_1)  where forward/backward-consistent and the
                     residual is above a threshold; elsewhere the Gaussian is static (zero flow)

Everything runs in the local frame of ``PairTensors`` (ego at keyframe 0).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch
import torch.nn.functional as F
from torch import Tensor

from drivingscene import kernels
from drivingscene.data.tensors import PairTensors
from drivingscene.gaussians.assembly import FootprintRule, gaussians_from_pixels, pixel_footprints
from drivingscene.gaussians.core import Gaussians
from drivingscene.geometry.camera import pixel_grid, scale_intrinsics
from drivingscene.geometry.flow import (
    FB_ALPHA,
    FB_BETA,
    backward_warp,
    forward_backward_consistency,
    forward_backward_consistency_at,
    inside_image,
    rigid_flow,
    sample_bilinear,
    vector_length,
)
from drivingscene.geometry.flow_search import flow_from_choice, luma, median_of_choice, search_along_rigid
from drivingscene.geometry.scene_flow import scene_flow_at_pixels, scene_flow_from_optical_flow
from drivingscene.geometry.se3 import rotate_vectors
from drivingscene.models.depth import DepthOutput
from drivingscene.models.gaussian_head import PixelGaussians
from drivingscene.models.matching import ViewGeometry, neighbour_views
from drivingscene.models.model import DrivingSceneModel
from drivingscene.render.composite import SURFACE_TOLERANCE
from drivingscene.render.sh import SH_C0

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


def sky_mask(depth: Tensor, intrinsics: Tensor, ref_focal: float, config: LiftConfig) -> Tensor:
    """``[..., V, H, W]`` bool: pixels treated as sky, for depth ``[..., V, H, W]``."""
    focal = intrinsics[:, 0, 0] / depth.shape[-1]
    threshold = config.sky_depth * focal / ref_focal  # [V]
    return depth > threshold[:, None, None]


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


def _resize_flow(flow: Tensor, size: tuple[int, int]) -> Tensor:
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
        rigid_chw = _resize_flow(rigid_chw, net_size)
    warped, _ = backward_warp(sources, rigid_chw.permute(0, 2, 3, 1))
    slots = model.camera_slots(batch.cam_to_ego).repeat(2)
    residuals = model.residual_flow(warped, targets, rigid_chw, slots, sources, finest_level, all_levels)
    if net_size != tuple(size):
        residuals = [_resize(r.float(), size, "bilinear") / to_net for r in residuals]
    residuals = [r.float().permute(0, 2, 3, 1).unflatten(0, (2, batch.num_views)) for r in residuals]
    warped = warped.unflatten(0, (2, batch.num_views))
    return FlowPrediction(rigid=rigid, residuals=residuals, warped_sources=warped, behind=behind)


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
        rigid_net, total_net = (_resize_flow(f.permute(0, 3, 1, 2), net_size).permute(0, 2, 3, 1) for f in (rigid, total))
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
) -> Gaussians:
    """Gaussians of the requested keyframes in the local frame, or the world frame with
    ``local_to_world`` (one pass, not a second transform of every Gaussian); sky pixels excluded.
    ``fit_colors`` > 0: that many iterations of the colour solve (`render.color_solve`) that makes
    each input image's own Gaussians re-render it (inference; training leaves the colours to P).
    ``footprints``: the footprint rule applied to P's scales (`gaussians.assembly`);
    ``surface_tolerance``: the own layer's rule the solve fits for (the layered blends')."""
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
