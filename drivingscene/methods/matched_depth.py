"""Depth from matching at inference: the network's depth corrected by what the two keyframes'
images triangulate along the known poses, at full image resolution.

D already matches across time and cameras (models/matching.py), but it learned to on procedural
streets only; a classical matcher does not need to learn what real texture looks like. After D:

    guide           = rigid_flows(depth)                        the network's depth and the poses
    total_k         = DIS(I_k, warp(I_{1-k}, guide)) o guide    guided OpenCV DIS, both directions
                                                                (`classical.dis_flows`)
    z, determined   = triangulate(total)                        forward/backward-consistent pixels on
                                                                their epipolar line with enough
                                                                parallax (`classical.triangulate`)
    log c           = smooth(log z - log depth | determined)    normalised Gaussian convolution of the
                                                                log ratio, coarse to fine
    depth'          = z where determined, depth * c elsewhere

Guided DIS echoes its guide where the image cannot say otherwise, so matching guided by D alone
confirms D's errors there. The default guide, "fallback", checks D's *shape* against what the
matching triangulates (`shape_dispersion`: the spread of log(z / depth) once the scale is
removed, over well-determined pixels): in a camera where D's own matches already scatter, the
keyframes are matched again guided by a prior that knows nothing of D (the road plane, 20 m
above the horizon), and in an image where the two guides' agreeing triangulations still disagree
with D's shape, the prior-guided triangulations fill in where D's guide determined nothing. On
images like the training data this costs little (few cameras are matched again); on real frames
it is where the accuracy comes from.

The correction is a smooth field, so D keeps the shape of what it sees where nothing matches
(sky, flat surfaces, straight ahead, moving objects: their flow is off the epipolar line) and
takes the scale of its matched neighbours; where no pixel within a few windows is determined the
depth is D's exactly. With the ego standing still nothing triangulates and the depth is D's,
unchanged. Sky (as D decides it) and pixels outside ``valid_mask`` are neither matched nor
corrected.

Chosen on validation pairs (``data/val176``, ``data/val176rand``; `drivingscene bench choices`,
docs/choices-matching.md), never on the test pairs or the real scene.

Why one file: it is one pipeline (guide, DIS both ways, triangulate, smooth the log ratio, fall
back where D disagrees) whose stages share the per-pair buffers and are called from nowhere else.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from kornia.filters import box_blur
from torch import Tensor

from drivingscene.data.frame_pair import FramePair
from drivingscene.data.resize import resized_pair
from drivingscene.data.road_plane import road_plane_depth
from drivingscene.data.tensors import PairTensors, pair_to_tensors
from drivingscene.geometry.flow import backward_warp
from drivingscene.methods.classical import DIS_PRESETS, dis_flows, triangulate
from drivingscene.methods.cross_camera import CrossCameraConfig, cross_camera_depth
from drivingscene.models.lift import LiftConfig
from drivingscene.models.pipeline import rigid_flows

GUIDES = ("depth", "prior", "both", "best", "fallback")
LEVELS = ("none", "image", "rig", "affine")
FUSES = ("time", "weighted")


@dataclass(frozen=True)
class MatchedDepthConfig:
    """Settings of `match_depth` (see the module docstring)."""

    # OpenCV DIS preset: "medium", "fast" or "ultrafast".
    preset: str = "medium"
    # What guides DIS (`classical.dis_flows`): "depth" (D's depth, then each pass's), "prior" (the
    # road plane below the horizon, ``prior_depth`` above it: knows nothing of D) or "both": a pixel
    # is determined only where both guides triangulate it within ``agree`` (relative) of each
    # other, at their geometric mean. Guided DIS returns its guide in flat regions, and a rigid
    # flow is forward/backward consistent and on the epipolar line: matching guided by D alone
    # can confirm D's error; two unrelated guides rarely echo the same wrong depth. "best": both
    # guides, and where both triangulate a pixel the match whose 5x5 patches differ less.
    # "fallback": D's guide first; in an image where D's shape is unreliable, the prior's where D's
    # does not triangulate a pixel. The shape's error is the median absolute deviation of
    # log(triangulated / D), scale removed (`shape_dispersion`), from ``fallback_dispersion`` on:
    # first over D's own matches, which picks the cameras whose prior-guided matching is run at
    # all (on images like the training data, few or none: the time is spent where it is needed),
    # then over the pixels where both guides triangulate the same depth (within ``agree``), which
    # neither guide's error explains (unreliable also where fewer than ``fallback_min_pixels``
    # agree).
    guide: str = "fallback"
    prior_depth: float = 20.0
    # DIS preset of the prior-guided matching (None: ``preset``).
    prior_preset: str | None = None
    fallback_dispersion: float = 0.1
    fallback_min_pixels: int = 50
    # ... measured where the triangulated depth is well determined: at least this many pixels of
    # parallax at the matching size (a pixel of flow error is then at most 1/8 of the depth; near the determination
    # threshold the triangulation's own noise would pass for D's error).
    fallback_parallax: float = 8.0
    agree: float = 0.1
    # Matching at this fraction of the image size (the images area-resized; the correction comes
    # back upsampled, and no pixel takes its triangulated depth as it is): 0.5 costs about a
    # quarter.
    scale: float = 1.0
    # Each further pass runs DIS again, guided by the previous pass's depth.
    passes: int = 1
    # Gaussian windows of the correction field (standard deviations, pixels at ``reference_width``
    # image columns, scaled with the width), applied coarse to fine: a finer window overrides a
    # coarser one in proportion to its support. 30 + 10 + 3 (docs/choices-matching.md run 8): the
    # 3 px window follows D's shape errors between nearby matches where a 10 px one averages them.
    sigmas: tuple[float, ...] = (30.0, 10.0, 3.0)
    reference_width: int = 320
    # Support (the window's weighted share of determined pixels) below ``min_support``: no
    # correction from that window; from there to ``full_support``: a linear ramp to all of it.
    min_support: float = 0.02
    full_support: float = 0.1
    # Coarser levels under the windows: "image", the image's median log ratio where at least
    # ``image_share`` of its pixels are determined; "rig", also the median over every image of the
    # keyframe for the images with fewer; "affine": "rig", but an image with at least that share
    # starts from a power law in D's depth instead of one scale (`affine_log_fit`: log z = a +
    # b log d, robustly fitted to its determined pixels, D's depth clamped to their range, so
    # that a D whose depth range is too compressed or too stretched is corrected where nothing
    # matches too), the windows then spreading what the law leaves; "none": the windows alone.
    levels: str = "rig"
    image_share: float = 0.01
    # Determined pixels take their triangulated depth (else only the smooth correction).
    replace: bool = True
    # Triangulation thresholds (`explain_by_parallax`), in image pixels: within ``epipolar_px``
    # of the epipolar line, ``epipolar_min_parallax`` from the point at infinite depth.
    lift: LiftConfig = field(default_factory=LiftConfig)
    # Stereo across the rig (`cross_camera.cross_camera_depth`) after the matching over time,
    # guided by its corrected depth: the pixels it triangulates and the time did not are added to
    # the determined ones and the correction is computed again. None: off.
    cross: CrossCameraConfig | None = field(default_factory=CrossCameraConfig)
    # Where both the time and the rig triangulate a pixel: "time" keeps the time's depth; "weighted"
    # takes the mean of the two log depths weighted by their parallax squared (a pixel of match
    # error moves log depth by about 1 / parallax: inverse-variance weights; docs/choices-matching.md
    # run 9).
    fuse: str = "weighted"
    # A moving object's depth from one instant, not from the time (issue 46): in an image where D's
    # shape agrees with the matches over time (`shape_dispersion` below ``fallback_dispersion``), a
    # pixel whose depth over time is more than this far from D's (|log ratio|, the image's median
    # ratio removed) is not determined by the time: what a static surface cannot explain there is
    # motion read as parallax (collinear traffic): it takes the correction of its neighbours, or the
    # rig's stereo depth. None: every triangulation over time kept (the default: with 0.3 the moving
    # objects' depth AbsRel 0.218 -> 0.186 on test pairs, but their pixels -0.32 dB there and the
    # real DDAD pair's in-between frame -0.10 dB; docs/moving-objects.md).
    prior_outlier: float | None = None
    # ... and those pixels follow the flow the matching found there (the inference lifts it with
    # their depth: a moving Gaussian where the time saw motion), never explained by parallax.
    refused_motion: bool = False

    def __post_init__(self):
        if self.prior_preset is not None and self.prior_preset not in DIS_PRESETS:
            raise ValueError(
                f"MatchedDepthConfig.prior_preset: expected one of {sorted(DIS_PRESETS)}, found {self.prior_preset!r}"
            )
        if self.preset not in DIS_PRESETS:
            raise ValueError(f"MatchedDepthConfig.preset: expected one of {sorted(DIS_PRESETS)}, found {self.preset!r}")
        if self.guide not in GUIDES:
            raise ValueError(f"MatchedDepthConfig.guide: expected one of {GUIDES}, found {self.guide!r}")
        if self.prior_outlier is not None and not self.prior_outlier > 0:
            raise ValueError(f"MatchedDepthConfig.prior_outlier: expected None or a log ratio > 0, found {self.prior_outlier}")
        if self.fuse not in FUSES:
            raise ValueError(f"MatchedDepthConfig.fuse: expected one of {FUSES}, found {self.fuse!r}")
        if self.levels not in LEVELS:
            raise ValueError(f"MatchedDepthConfig.levels: expected one of {LEVELS}, found {self.levels!r}")
        if not 0.0 < self.scale <= 1.0:
            raise ValueError(f"MatchedDepthConfig.scale: expected a fraction in (0, 1], found {self.scale}")
        if self.passes < 1:
            raise ValueError(f"MatchedDepthConfig.passes: expected >= 1, found {self.passes}")
        if not self.sigmas or min(self.sigmas) <= 0:
            raise ValueError(f"MatchedDepthConfig.sigmas: expected positive widths, found {self.sigmas}")
        if not 0.0 <= self.min_support < self.full_support <= 1.0:
            raise ValueError(
                "MatchedDepthConfig: expected 0 <= min_support < full_support <= 1, "
                f"found {self.min_support} and {self.full_support}"
            )


def match_mode(mode: str) -> MatchedDepthConfig | None:
    """The config of a ``--match`` mode (`drivingscene reconstruct`; the CLI lists the modes
    without importing torch): ``fallback`` the defaults (over time with the road-plane fallback,
    then stereo across the rig), ``time`` the same without the stereo across the rig, ``depth``
    over time guided by D only (no road-plane fallback, no stereo), ``off`` None (D's depth as it
    is)."""
    modes = {
        "fallback": MatchedDepthConfig(),
        "time": MatchedDepthConfig(cross=None),
        "depth": MatchedDepthConfig(guide="depth", cross=None),
        "off": None,
    }
    if mode not in modes:
        raise ValueError(f"match mode: expected one of {', '.join(modes)}, found {mode!r}")
    return modes[mode]


def smooth_log_correction(
    log_ratio: np.ndarray,  # [N, H, W] float32, anything where not determined
    determined: np.ndarray,  # [N, H, W] bool
    sigmas: tuple[float, ...],  # pixels
    min_support: float,
    full_support: float,
    image_share: float = 0.0,
    base: np.ndarray | None = None,
    fitted: np.ndarray | None = None,
) -> np.ndarray:
    """``[N, H, W]`` float32: the log ratio spread from the determined pixels by normalised
    Gaussian convolution, coarse to fine, faded out where the support is low (0 there); with
    ``image_share`` > 0, an image with at least that share of determined pixels starts from their
    median (one scale for the whole image) instead of 0, or instead of ``base[i]`` where given;
    images ``fitted`` ``[N]`` (a level fitted and removed beforehand) start from 0."""
    out = np.zeros(log_ratio.shape, np.float32)
    if base is not None:
        out += np.asarray(base, np.float32).reshape(-1, 1, 1)
    for i in range(len(log_ratio)):
        weight = determined[i].astype(np.float32)
        if not weight.any():
            continue
        if fitted is not None and fitted[i]:
            out[i] = 0.0
        elif image_share > 0 and weight.mean() >= image_share:
            out[i] = np.median(log_ratio[i][determined[i]])
        stack = np.stack([np.where(determined[i], log_ratio[i], 0.0).astype(np.float32) * weight, weight], -1)
        for sigma in sorted(sigmas, reverse=True):
            num, den = _gaussian_blur(stack, sigma).transpose(2, 0, 1)
            ramp = np.clip((den - min_support) / (full_support - min_support), 0.0, 1.0)
            out[i] += ramp * (num / np.maximum(den, 1e-6) - out[i])
    return out


def affine_log_fit(
    log_d: np.ndarray,  # [2, V, H, W] log of D's depth
    log_ratio: np.ndarray,  # [2, V, H, W] log(triangulated / D) where determined
    determined: np.ndarray,  # [2, V, H, W] bool
    image_share: float,
    min_pixels: int = 200,
    iterations: int = 3,
) -> tuple[np.ndarray, np.ndarray]:
    """``[2, V, H, W]`` float32 and ``[2, V]`` bool, where fitted: per image with at least
    ``image_share`` (and ``min_pixels``) of its
    pixels determined, the log ratio a + (b - 1) log d of the power law log z = a + b log d,
    fitted to the determined pixels by least squares on the inliers of the previous fit (within
    2.5 robust standard deviations of its median residual; the first fit is one scale, the
    median), ``iterations`` times, b clamped to [0.5, 2] and D's
    log depth clamped to the 2nd-98th percentile of the determined pixels' (no extrapolation
    beyond what was matched); 0 in the other images."""
    out = np.zeros(log_d.shape, np.float32)
    fitted = np.zeros(log_d.shape[:2], bool)
    for k, v in np.ndindex(*log_d.shape[:2]):
        mask = determined[k, v]
        count = int(mask.sum())
        if count < max(min_pixels, image_share * mask.size):
            continue
        x, y = log_d[k, v][mask].astype(np.float64), log_ratio[k, v][mask].astype(np.float64)
        lo, hi = np.percentile(x, [2.0, 98.0])
        x = np.clip(x, lo, hi)
        centre = float(np.median(x))
        x = x - centre
        slope, offset = 0.0, float(np.median(y))
        for _ in range(iterations):  # from one scale (slope 0): the inliers of each fit make the next
            residual = y - (offset + slope * x)
            mad = float(np.median(np.abs(residual - np.median(residual))))
            inliers = np.abs(residual - np.median(residual)) <= 2.5 * 1.4826 * max(mad, 1e-3)
            xs, ys = x[inliers], y[inliers]
            if len(xs) < 10:
                break
            spread = float(np.mean(xs * xs) - np.mean(xs) ** 2)
            if spread < 1e-6:
                break
            slope = float(np.clip(np.mean(xs * ys) - np.mean(xs) * np.mean(ys), -0.5 * spread, 1.0 * spread) / spread)
            offset = float(np.mean(ys) - slope * np.mean(xs))
        out[k, v] = offset + slope * (np.clip(log_d[k, v], lo, hi) - centre)
        fitted[k, v] = True
    return out, fitted


def _gaussian_blur(image: np.ndarray, sigma: float) -> np.ndarray:
    """``image`` ``[H, W, C]`` float32 blurred with a Gaussian of ``sigma`` pixels (reflected
    borders). Wide windows are blurred at a fraction of the size (area-averaged, at least 2.5 px
    of sigma left) and brought back bilinearly: a smooth result, at a few times less cost."""
    height, width = image.shape[:2]
    factor = int(sigma // BLUR_SIGMA_AT_SIZE)
    if factor < 2 or min(height, width) < 8 * factor:
        return cv2.GaussianBlur(image, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
    size = (max(1, round(width / factor)), max(1, round(height / factor)))
    small = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
    small = cv2.GaussianBlur(small, (0, 0), sigma * size[0] / width, borderType=cv2.BORDER_REFLECT)
    return cv2.resize(small, (width, height), interpolation=cv2.INTER_LINEAR).reshape(image.shape)


# Wide Gaussian windows are blurred at a reduced size with at least this sigma (pixels) left.
BLUR_SIGMA_AT_SIZE = 2.5


def _patch_cost(image: Tensor, other: Tensor, flow: Tensor) -> Tensor:
    """``[V, H, W]``: mean |image - other sampled along flow| over 5x5 windows (grey images ``[V, H, W]``)."""
    warped, _ = backward_warp(other[:, None], flow)
    diff = (image[:, None] - warped).abs()
    return box_blur(diff, (5, 5), border_type="replicate")[:, 0]


def _select_views(batch: PairTensors, views: list[int]) -> PairTensors:
    """The keyframes' tensors of ``batch`` for the cameras ``views`` only (no evaluation frames or ground truth)."""
    return PairTensors(
        images=batch.images[:, views],
        intrinsics=batch.intrinsics[views],
        cam_to_ego=batch.cam_to_ego[views],
        cam_to_local=batch.cam_to_local[:, views],
        local_to_world=batch.local_to_world,
        valid_mask=None if batch.valid_mask is None else batch.valid_mask[views],
    )


def _agree(z: Tensor, other: Tensor, tolerance: float) -> Tensor:
    """Where two triangulated depths agree within ``tolerance`` (relative, in log depth)."""
    return (z.clamp_min(1e-3) / other.clamp_min(1e-3)).log().abs() <= np.log1p(tolerance)


def shape_dispersion(d: Tensor, z: Tensor, where: Tensor, min_pixels: int) -> Tensor:
    """``[2, V]``: per image, the median absolute deviation of log(z / d) over the pixels ``where``
    (the scale removed: how far D's *shape* is from the triangulated one); NaN with fewer than
    ``min_pixels`` pixels."""
    log_ratio = (z.clamp_min(1e-3) / d.clamp_min(1e-3)).log().flatten(2).numpy()
    mask = where.flatten(2).numpy()
    out = np.full(mask.shape[:2], np.nan, np.float32)
    for k, v in np.argwhere(mask.sum(-1) >= max(min_pixels, 1)):  # the pixels of one image, then two lower medians
        values = log_ratio[k, v][mask[k, v]]
        out[k, v] = _lower_median(np.abs(values - _lower_median(values)))
    return torch.from_numpy(out)


def _lower_median(values: np.ndarray) -> np.float32:
    """The lower of the two middle values for an even count (torch's ``median``), by partition."""
    middle = (len(values) - 1) // 2
    return np.partition(values, middle)[middle]


@torch.no_grad()
def match_depth(
    depth: Tensor,  # [2, V, H, W] z-depth (metres), any device
    excluded: Tensor,  # [2, V, H, W] bool: sky and pixels that do not see the world
    pair: FramePair,
    batch: PairTensors,
    config: MatchedDepthConfig = MatchedDepthConfig(),
    with_motion: bool = False,
) -> tuple[Tensor, Tensor, dict[str, float]] | tuple[Tensor, Tensor, dict[str, float], Tensor, Tensor]:
    """The corrected depth (same dtype and device), the ``[2, V, H, W]`` mask of pixels that took
    a triangulated depth, and timings (flow, triangulation, correction); ``with_motion``: also the
    mask of pixels whose triangulation over time was refused as motion
    (`MatchedDepthConfig.prior_outlier`) and the flow matched there ``[2, V, H, W, 2]`` (0 elsewhere)."""
    device, dtype = depth.device, depth.dtype
    d = depth.detach().float().cpu()
    keep = (~excluded).cpu()
    timings = dict.fromkeys(
        ("match_flow_s", "match_triangulate_s", "match_correct_s", "match_cross_s", "match_fallback_views"), 0.0
    )
    if config.scale == 1.0:
        cpu = batch.to("cpu") if device.type != "cpu" else batch
        out, determined, refused, motion = _match(d, keep, pair, cpu, config, timings)
    else:
        small = resized_pair(pair, config.scale)
        size = small.image_size
        d_small = F.interpolate(d.flatten(0, 1)[:, None], size, mode="nearest")[:, 0].view(*d.shape[:2], *size)
        keep_small = F.interpolate(keep.flatten(0, 1)[:, None].float(), size, mode="nearest")[:, 0].view(d_small.shape) > 0.5
        small_batch = pair_to_tensors(small, with_gt=False, with_eval=False)
        out_small, _, _, _ = _match(d_small, keep_small, small, small_batch, replace(config, replace=False), timings)
        t0 = time.perf_counter()
        log_ratio = (out_small.clamp_min(1e-3) / d_small.clamp_min(1e-3)).log().flatten(0, 1)[:, None]
        log_ratio = F.interpolate(log_ratio, d.shape[-2:], mode="bilinear", align_corners=False)[:, 0].view_as(d)
        out = torch.where(keep, d * log_ratio.exp(), d)
        determined = refused = torch.zeros_like(keep)
        motion = torch.zeros((*d.shape, 2))
        timings["match_correct_s"] += time.perf_counter() - t0
    out, determined = out.to(device=device, dtype=dtype), determined.to(device)
    if with_motion:
        return out, determined, timings, refused.to(device), motion.to(device)
    return out, determined, timings


def _match(
    d: Tensor, keep: Tensor, pair: FramePair, cpu: PairTensors, config: MatchedDepthConfig, timings: dict[str, float]
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """`match_depth` at the pair's own size, on the CPU: the corrected depth, the determined mask,
    the refused mask and the flow matched at the refused pixels (0 elsewhere)."""
    scale = d.shape[-1] / config.reference_width
    out = d
    grey = cpu.images.float().mean(2)  # [2, V, H, W]

    def triangulated_with(
        guide_depth: Tensor, preset: str, views: list[int] | None = None
    ) -> tuple[Tensor, Tensor, Tensor | None, Tensor | None, Tensor | None, Tensor]:
        """Triangulated depth, determined mask, (``guide="best"``) patch costs, (``guide="fallback"``)
        the well-determined mask, (``guide="fallback"`` or ``fuse="weighted"``) each pixel's
        parallax and the flow matched; with ``views``, only those cameras are matched (the others
        determine nothing, flow 0)."""
        t0 = time.perf_counter()
        sub, images, world, depth_sub = cpu, pair.images, keep, d
        if views is not None:
            sub = _select_views(cpu, views)
            images, world, depth_sub, guide_depth = pair.images[:, views], keep[:, views], d[:, views], guide_depth[:, views]
        guide = rigid_flows(guide_depth, sub).float()
        total = torch.from_numpy(dis_flows(images, preset, guide.numpy()))
        t1 = time.perf_counter()
        well = parallax = None
        if config.guide == "fallback" or config.fuse == "weighted":
            z, _, parallax = triangulate(total, world, sub, config.lift, with_parallax=True)
            if config.guide == "fallback":
                well = (z > 0) & (parallax >= config.fallback_parallax)
        else:
            z, _ = triangulate(total, world, sub, config.lift)
        cost = None
        if config.guide == "best":
            cost = torch.stack([_patch_cost(grey[k], grey[1 - k], total[k]) for k in (0, 1)])
        determined = (z > 0) & world & (depth_sub > 0)
        if views is not None:
            index = torch.tensor(views)
            z = torch.zeros_like(d).index_copy_(1, index, z)
            determined = torch.zeros_like(keep).index_copy_(1, index, determined)
            well = None if well is None else torch.zeros_like(keep).index_copy_(1, index, well)
            parallax = None if parallax is None else torch.zeros_like(d).index_copy_(1, index, parallax.float())
            total = torch.zeros((*d.shape, 2)).index_copy_(1, index, total.float())
        timings["match_flow_s"] += t1 - t0
        timings["match_triangulate_s"] += time.perf_counter() - t1
        return z, determined, cost, well, parallax, total

    def prior_guide() -> Tensor:
        road = torch.from_numpy(road_plane_depth(pair, far=config.lift.epipolar_far))
        return torch.where(road >= config.lift.epipolar_far, torch.full_like(road, config.prior_depth), road)

    prior = None
    if config.guide in ("prior", "both", "best"):
        prior = triangulated_with(prior_guide(), config.prior_preset or config.preset)
    held = torch.zeros_like(keep)  # refused as motion (`MatchedDepthConfig.prior_outlier`) ...
    motion = None  # ... and the flow matched there (None: nothing refused)
    for step in range(config.passes):
        if config.guide == "prior":
            triangulated, determined, _, _, parallax, matched_flow = prior
        else:
            triangulated, determined, cost, well, parallax, matched_flow = triangulated_with(out, config.preset)
        if config.guide == "both":
            z_prior, determined_prior, _, _, _, _ = prior
            agree = (triangulated.clamp_min(1e-3) / z_prior.clamp_min(1e-3)).log().abs() <= np.log1p(config.agree)
            determined = determined & determined_prior & agree
            triangulated = torch.where(determined, (triangulated * z_prior).sqrt(), torch.zeros_like(triangulated))
        elif config.guide == "fallback":
            # the prior's matching only for the cameras where D's own matches already scatter
            suspect = shape_dispersion(d, triangulated, well, config.fallback_min_pixels) >= config.fallback_dispersion
            views = [v for v in range(d.shape[1]) if bool(suspect[:, v].any())]
            timings["match_fallback_views"] = float(len(views))
            if views:
                if prior is None:
                    prior = triangulated_with(prior_guide(), config.prior_preset or config.preset, views)
                z_prior, determined_prior, _, _, parallax_prior, _ = prior
                agree = well & determined_prior & _agree(triangulated, z_prior, config.agree)
                dispersion = shape_dispersion(d, triangulated, agree, config.fallback_min_pixels)
                unreliable = dispersion.isnan() | (dispersion >= config.fallback_dispersion)
                extra = determined_prior & ~determined & unreliable[..., None, None]
                triangulated = torch.where(extra, z_prior, triangulated)
                parallax = torch.where(extra, parallax_prior, parallax)
                determined = determined | extra
        elif config.guide == "best":
            z_prior, determined_prior, cost_prior, _, parallax_prior, _ = prior
            take_prior = determined_prior & (~determined | (cost_prior < cost))
            triangulated = torch.where(take_prior, z_prior, triangulated)
            if parallax is not None:
                parallax = torch.where(take_prior, parallax_prior, parallax)
            determined = determined | determined_prior
        if config.prior_outlier is not None:
            refused = _prior_outliers(d, triangulated, determined, well, config)
            determined = determined & ~refused
            motion = torch.where(refused[..., None], matched_flow, 0.0 if motion is None else motion)
            held = held | refused
        if config.cross is not None and step == config.passes - 1:
            # overlapping cameras of each keyframe, guided by this pass's depth: stereo across the
            # rig where the ego's motion gave no parallax
            t0 = time.perf_counter()
            z_cross, parallax_cross, _ = cross_camera_depth(
                _rescaled(out, triangulated, determined), keep, pair.images, cpu, config.lift, config.cross
            )
            if config.fuse == "weighted" and parallax is not None:
                triangulated = _fused(triangulated, parallax, z_cross, parallax_cross, determined & (z_cross > 0))
            extra = (z_cross > 0) & ~determined
            triangulated = torch.where(extra, z_cross, triangulated)
            determined = determined | extra
            timings["match_cross_s"] += time.perf_counter() - t0
        t2 = time.perf_counter()
        out = _corrected(d, keep, triangulated, determined, config, scale)
        timings["match_correct_s"] += time.perf_counter() - t2
    held = held & ~determined  # the rig's stereo may have determined some
    return out, determined, held, torch.zeros((*d.shape, 2)) if motion is None else motion


def _prior_outliers(d: Tensor, z: Tensor, determined: Tensor, well: Tensor | None, config: MatchedDepthConfig) -> Tensor:
    """``[2, V, H, W]``: the determined pixels of the images where D's shape is reliable whose
    triangulated depth ``z`` is more than ``config.prior_outlier`` from D's ``d`` in log depth, each
    image's median log ratio removed (`MatchedDepthConfig.prior_outlier`)."""
    where = determined if well is None else well & determined
    reliable = shape_dispersion(d, z, where, config.fallback_min_pixels) < config.fallback_dispersion  # NaN: False
    log_ratio = (z.clamp_min(1e-3) / d.clamp_min(1e-3)).log()
    out = torch.zeros_like(determined)
    for k, v in reliable.nonzero().tolist():
        mask = determined[k, v]
        centre = float(_lower_median(log_ratio[k, v][mask].numpy()))
        out[k, v] = mask & ((log_ratio[k, v] - centre).abs() > config.prior_outlier)
    return out


def _corrected(
    d: Tensor, keep: Tensor, triangulated: Tensor, determined: Tensor, config: MatchedDepthConfig, scale: float
) -> Tensor:
    """D's depth ``d`` times the smooth correction field that the triangulated depth of the
    determined pixels gives (see `MatchedDepthConfig`), and the triangulated depth itself where
    determined (``replace``)."""
    log_ratio = (triangulated.clamp_min(1e-3) / d.clamp_min(1e-3)).log()
    base = None
    if config.levels in ("rig", "affine"):  # per keyframe: the median over its images' determined pixels
        base = np.repeat(_keyframe_log_scales(log_ratio, determined, config.image_share)[:, None], determined.shape[1], 1)
    law = fitted = None  # "affine": the law is removed before the windows and added after them
    if config.levels == "affine":
        law, fitted = affine_log_fit(d.clamp_min(1e-3).log().numpy(), log_ratio.numpy(), determined.numpy(), config.image_share)
    target = log_ratio if law is None else log_ratio - torch.from_numpy(law)
    correction = smooth_log_correction(
        target.flatten(0, 1).numpy(),
        determined.flatten(0, 1).numpy(),
        tuple(s * scale for s in config.sigmas),
        config.min_support,
        config.full_support,
        config.image_share if config.levels != "none" else 0.0,
        None if base is None else base.reshape(-1),
        fitted=None if fitted is None else fitted.reshape(-1),
    )
    if law is not None:  # 0 where not fitted
        correction = correction + law.reshape(correction.shape)
    out = torch.where(keep, d * torch.from_numpy(correction).view_as(d).exp(), d)
    if config.replace:
        out = torch.where(determined, triangulated, out)
    return out


def _fused(z: Tensor, parallax: Tensor, z_other: Tensor, parallax_other: Tensor, both: Tensor) -> Tensor:
    """``z`` where not ``both``; there, the mean of log ``z`` and log ``z_other`` weighted by their
    parallax squared."""
    w, w_other = parallax.float().square(), parallax_other.float().square()
    log_mean = (w * z.clamp_min(1e-3).log() + w_other * z_other.clamp_min(1e-3).log()) / (w + w_other).clamp_min(1e-12)
    return torch.where(both & (w + w_other > 0), log_mean.exp(), z)


def _keyframe_log_scales(log_ratio: Tensor, determined: Tensor, min_share: float) -> np.ndarray:
    """``[2]`` float32: per keyframe, the (lower) median of ``log_ratio`` ``[2, V, H, W]`` over its
    determined pixels, where they are at least ``min_share`` of its pixels (and any), else 0."""
    out = np.zeros(2, np.float32)
    for k in (0, 1):
        where = determined[k].numpy()
        if where.any() and where.mean() >= min_share:
            out[k] = _lower_median(log_ratio[k].numpy()[where])
    return out


def _rescaled(depth: Tensor, triangulated: Tensor, determined: Tensor) -> Tensor:
    """``depth`` ``[2, V, H, W]`` times, per keyframe, the median ratio of the triangulated depth to
    it over the determined pixels (as it is where none are)."""
    log_ratio = (triangulated.clamp_min(1e-3) / depth.clamp_min(1e-3)).log()
    scales = torch.from_numpy(np.exp(_keyframe_log_scales(log_ratio, determined, 0.0)))
    return depth * scales.view(2, 1, 1, 1)
