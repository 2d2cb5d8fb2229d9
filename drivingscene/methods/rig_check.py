"""Is a scene's geometry consistent with its images? A check of the poses, the extrinsics and
the LiDAR of an imported pair, camera by camera, with no network.

Everything the model does across time and cameras trusts the scene's geometry: a camera whose
``cam_to_ego`` is a degree off, a wrong camera timestamp or a LiDAR in the wrong frame do not
raise an error, they quietly make the matching, the depth and the in-between frame worse. Two
tests say which image disagrees with the others:

- **Epipolar residual.** Each camera's image at one keyframe is matched to the same camera's
  image at the other by OpenCV's DIS optical flow, unguided (a guide from the poses would pull
  the matches onto the very lines under test). Where a match is forward/backward consistent and
  the image has texture, the poses predict a line that its end point must lie on, whatever the
  depth (`models.lift.epipolar_geometry`). The median distance from that line, in the
  scene's pixels, is DIS's own error (well under a pixel) where the geometry is right; a rotation
  error of the camera's extrinsics, or of the ego's motion between the images, moves every line
  and shows as pixels. Moving objects are off their lines too, which the median ignores while
  they are under half of the matches.
- **LiDAR scale** (where the scene has ``gt_depth``). Each LiDAR return with texture around it
  predicts where its 5x5 patch lies in the other keyframe's image of the same camera; the check
  slides every return's depth by a common factor (0.5-2, in 1 % steps) and takes the factor at
  which the patches agree best (median absolute grey difference). With the LiDAR, the
  extrinsics and the poses right, that factor is 1: a LiDAR whose points land on the wrong
  pixels, or a pose whose baseline is too long or too short, move it.

A camera whose keyframes have next to no baseline (the ego standing still) says nothing about
either and is reported so. The thresholds (``RigCheckConfig``) are chosen from the procedural
pairs, whose geometry is exact, and from those pairs with one camera's extrinsics rotated
(tests/methods/test_rig_check.py); docs/importing.md shows the real DDAD pair.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import cv2
import numpy as np
import torch

from drivingscene.data.frame_pair import FramePair
from drivingscene.data.resize import resized_pair
from drivingscene.data.road_plane import road_plane_depth
from drivingscene.data.tensors import pair_to_tensors
from drivingscene.geometry.flow import forward_backward_consistency, rigid_flow
from drivingscene.methods.classical import dis_flows
from drivingscene.models.lift import epipolar_geometry
from drivingscene.models.pipeline import rigid_flows

# The depth of the motion prior: the road plane, capped at this depth, and this depth at and above
# the horizon (the matching at inference guides by the same depth above the horizon,
# `MatchedDepthConfig.prior_depth`, but keeps the road out to its far limit).
PRIOR_DEPTH_M = 20.0


@dataclass(frozen=True)
class RigCheckConfig:
    preset: str = "medium"  # DIS preset of the matching
    # Pixels whose grey level changes by at least this much (0-255, Sobel magnitude / 8: the mean
    # difference over one pixel) are textured: matches and patches are only trusted there.
    min_texture: float = 4.0
    min_matches: int = 200  # fewer consistent textured matches: nothing to say
    # Median distance from the epipolar line (pixels at the checked size, `max_width`) from which an
    # image is reported.
    max_off_line_px: float = 1.0
    min_baseline_m: float = 0.05  # camera motion between the keyframes below which nothing is tested
    # Unguided DIS does not follow motions of many tens of pixels (side cameras of keyframes 0.5 s
    # apart move 100-300 px at 320 wide): an image whose expected motion (the median rigid flow of
    # the road plane, 20 m above the horizon, by the scene's own poses) is larger is not put to the
    # epipolar test; the LiDAR test, which needs no matching, still runs. 25 px: the largest
    # setting at which no image of 40 procedural pairs (exact geometry) was reported
    # (`drivingscene bench geometry`, docs/importing.md).
    max_motion_px: float = 25.0
    # A camera that moves faster than this between the keyframes (metres per second, from the
    # poses and the keyframes' timestamps) is reported: no car does (millimetres given as metres,
    # or timestamps in another unit, say).
    max_speed_mps: float = 100.0
    # An image is reported when fewer of its matches than this triangulate in front of both
    # cameras (a camera looking the other way, images of two cameras swapped).
    min_in_front: float = 0.5
    # LiDAR: the factors tried (0.5-2 in steps of 5 %, then 1 % steps around the best), at most
    # ``max_returns`` returns per image (evenly spaced), and how far from 1 the best may be
    # before the image is reported.
    max_scale: float = 2.0
    coarse_step: float = 0.05
    fine_step: float = 0.01
    max_scale_error: float = 0.1
    clear_minimum: float = 0.8  # the coarse search's least cost must be below this times its median
    min_returns: int = 100
    max_returns: int = 2000
    window: int = 5  # the patch compared around each return
    # Wider scenes are checked at this width (images area-resized, each LiDAR return moved to its
    # pixel there, the nearest kept), so that the pixel thresholds keep one meaning (DIS's error
    # is about constant in pixels, a geometric error grows with the image) and DIS on full-size
    # images does not take seconds per image.
    max_width: int = 320


@dataclass(frozen=True)
class ImageCheck:
    camera: str
    keyframe: int
    baseline_m: float  # how far the camera moved to the other keyframe
    motion_px: float  # the image's expected motion (median, pixels at the checked size)
    matches: int  # consistent textured matches to the other keyframe
    in_front: float | None  # the share of them that triangulates in front of both cameras
    off_line_px: float | None  # their median distance from the epipolar line (those in front)
    within_1px: float | None  # the share within one pixel of it
    returns: int  # textured LiDAR returns
    lidar_scale: float | None  # the depth factor at which they agree best with the other keyframe (None: no clear best)
    verdict: str  # "ok", or what is wrong, or why nothing could be said

    @property
    def flagged(self) -> bool:
        return self.verdict not in ("ok", "no baseline", "too little texture", "motion too large")

    @property
    def tested(self) -> bool:
        """Whether either test could say something about the image."""
        return self.off_line_px is not None or self.lidar_scale is not None


@dataclass
class GeometrySummary:
    """What the checks of one scene come to: the images, those tested, one line per image that disagrees."""

    images: int
    tested: int
    problems: list[str]

    def describe(self) -> str:
        """In a few words (the viewer's Scene panel)."""
        if self.problems:
            return f"{len(self.problems)} of {self.images} images disagree"
        if self.tested:
            return f"consistent ({self.tested} of {self.images} images tested)"
        return "not tested (no motion or texture to test it)"


def summarise(checks: list[ImageCheck]) -> GeometrySummary:
    """A `GeometrySummary` of ``checks`` (`problem_line` per flagged image)."""
    return GeometrySummary(len(checks), sum(c.tested for c in checks), [problem_line(c) for c in checks if c.flagged])


def _grey(image: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2GRAY).astype(np.float32)


def _textured(grey: np.ndarray, threshold: float) -> np.ndarray:
    gx = cv2.Sobel(grey, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(grey, cv2.CV_32F, 0, 1, ksize=3)
    return np.hypot(gx, gy) / 8.0 >= threshold


def patch_difference(
    grey: np.ndarray,  # [H, W] this keyframe's image
    other: np.ndarray,  # [H, W] the same camera at the other keyframe
    flow: np.ndarray,  # [N, 2] each return's flow
    ys: np.ndarray,
    xs: np.ndarray,  # [N] the returns' pixels
    window: int,
) -> float:
    """The median over returns of the mean absolute grey difference between the return's
    ``window`` x ``window`` patch and the other image sampled at the patch moved by the return's
    flow (the patch taken as fronto-parallel)."""
    height, width = grey.shape
    half = window // 2
    total = np.zeros(len(ys), np.float32)
    for dy in range(-half, half + 1):
        for dx in range(-half, half + 1):
            yy, xx = np.clip(ys + dy, 0, height - 1), np.clip(xs + dx, 0, width - 1)
            map_x = (xx + flow[:, 0]).astype(np.float32)[:, None]
            map_y = (yy + flow[:, 1]).astype(np.float32)[:, None]
            sampled = cv2.remap(other, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)[:, 0]
            total += np.abs(grey[yy, xx] - sampled)
    return float(np.median(total / window**2))


def best_lidar_scale(
    pair: FramePair, batch, greys: list, k: int, v: int, ys: np.ndarray, xs: np.ndarray, config: RigCheckConfig
) -> float | None:
    """The factor of the returns' depth at which their patches agree best with the other
    keyframe (`patch_difference`): a coarse search, then a fine one around its best. None where
    the coarse search has no clear minimum: at an end of its range, or above ``clear_minimum``
    times its median (an image without enough texture, or motion too large for the window)."""
    depth = torch.zeros((1, *pair.image_size))
    depth[0, ys, xs] = torch.from_numpy(pair.gt_depth[k, v, ys, xs]).float()
    c2l, intrinsics = batch.cam_to_local.float(), batch.intrinsics[v : v + 1].float()

    def curve(centre: float, step: float, count: int) -> tuple[np.ndarray, np.ndarray]:
        factors = centre * np.exp(np.log1p(step) * np.arange(-count, count + 1))
        costs = []
        for factor in factors:
            flow, _ = rigid_flow(depth * float(factor), intrinsics, c2l[k, v : v + 1], c2l[1 - k, v : v + 1])
            costs.append(patch_difference(greys[k][v], greys[1 - k][v], flow[0].numpy()[ys, xs], ys, xs, config.window))
        return factors, np.asarray(costs)

    factors, costs = curve(1.0, config.coarse_step, int(np.ceil(np.log(config.max_scale) / np.log1p(config.coarse_step))))
    best = int(np.argmin(costs))
    if best in (0, len(costs) - 1) or costs[best] > config.clear_minimum * np.median(costs):
        return None
    factors, costs = curve(
        float(factors[best]), config.fine_step, int(np.ceil(np.log1p(config.coarse_step) / np.log1p(config.fine_step)))
    )
    return float(factors[int(np.argmin(costs))])


def checked_size(pair: FramePair, max_width: int) -> FramePair:
    """``pair`` as it is checked: resized to ``max_width`` where it is wider (`resized_pair`), its
    LiDAR depth carried along (each return to the pixel of the smaller image that holds its
    centre, the nearest where several land on one)."""
    height, width = pair.image_size
    if width <= max_width:
        return pair
    small = resized_pair(pair, max_width / width)
    if pair.gt_depth is None:
        return small
    h, w = small.image_size
    depth = np.full((2, pair.num_views, h, w), np.inf, np.float32)
    k, v, y, x = np.nonzero(pair.gt_depth > 0)
    ys = np.clip(np.round((y + 0.5) * h / height - 0.5).astype(np.int64), 0, h - 1)
    xs = np.clip(np.round((x + 0.5) * w / width - 0.5).astype(np.int64), 0, w - 1)
    np.minimum.at(depth, (k, v, ys, xs), pair.gt_depth[k, v, y, x])
    return dataclasses.replace(small, gt_depth=np.where(np.isfinite(depth), depth, 0.0).astype(np.float32))


def check_rig(pair: FramePair, config: RigCheckConfig = RigCheckConfig()) -> list[ImageCheck]:
    """One `ImageCheck` per keyframe and camera (keyframe-major), as the module docstring says,
    on the pair at most ``config.max_width`` wide (`checked_size`)."""
    pair = checked_size(pair, config.max_width)
    batch = pair_to_tensors(pair, with_gt=pair.gt_depth is not None, with_eval=False)
    c2l = batch.cam_to_local.double()
    flows = torch.from_numpy(dis_flows(pair.images, config.preset))  # [2, V, H, W, 2], unguided
    greys = [[_grey(image) for image in keyframe] for keyframe in pair.images]
    world = np.ones((pair.num_views, *pair.image_size), bool) if pair.valid_mask is None else pair.valid_mask
    road = torch.from_numpy(road_plane_depth(pair, far=PRIOR_DEPTH_M + 1.0))
    prior = torch.where(road > PRIOR_DEPTH_M, torch.full_like(road, PRIOR_DEPTH_M), road)
    expected = rigid_flows(prior, batch).norm(dim=-1)  # [2, V, H, W]
    out = []
    for k in (0, 1):
        rel = (torch.linalg.inv(c2l[1 - k]) @ c2l[k]).float()  # [V, 4, 4] this keyframe's camera -> the other's
        baselines = rel[:, :3, 3].norm(dim=-1)
        consistent = forward_backward_consistency(flows[k], flows[1 - k]).numpy()
        _, off_line, _, valid = epipolar_geometry(flows[k].float(), batch.intrinsics.float(), rel)
        for v in range(pair.num_views):
            baseline = float(baselines[v])
            motion = float(expected[k, v][torch.from_numpy(world[v])].median()) if world[v].any() else 0.0
            textured = _textured(greys[k][v], config.min_texture) & world[v]
            matched = textured & consistent[v]
            matches = int(matched.sum())
            front = off = within = None
            if matches >= config.min_matches and motion <= config.max_motion_px:
                use = matched & valid[v].numpy()
                front = float(use.sum() / matches)
                if use.sum() >= config.min_matches:
                    distances = off_line[v].numpy()[use]
                    off, within = float(np.median(distances)), float(np.mean(distances <= 1.0))
            returns, best = 0, None
            if pair.gt_depth is not None:
                ys, xs = np.nonzero((pair.gt_depth[k, v] > 0) & textured)
                returns = len(ys)
                if returns >= config.min_returns and baseline >= config.min_baseline_m:
                    keep = np.linspace(0, returns - 1, min(returns, config.max_returns)).round().astype(np.int64)
                    best = best_lidar_scale(pair, batch, greys, k, v, ys[keep], xs[keep], config)
            speed = baseline / max(pair.duration, 1e-9)
            verdict = _verdict(baseline, speed, motion, front, off, best, config)
            out.append(
                ImageCheck(
                    pair.camera_names[v],
                    k,
                    round(baseline, 3),
                    round(motion, 1),
                    matches,
                    front,
                    off,
                    within,
                    returns,
                    best,
                    verdict,
                )
            )
    return out


def _verdict(
    baseline: float,
    speed: float,
    motion: float,
    front: float | None,
    off: float | None,
    scale: float | None,
    config: RigCheckConfig,
) -> str:
    if baseline < config.min_baseline_m:
        return "no baseline"
    problems = []
    if speed > config.max_speed_mps:
        problems.append("implausible motion")
    if front is not None and front < config.min_in_front:
        problems.append("matches behind the cameras")
    if off is not None and off > config.max_off_line_px:
        problems.append("off the epipolar lines")
    if scale is not None and abs(np.log(scale)) > np.log1p(config.max_scale_error):
        problems.append("LiDAR scale")
    if problems:
        return ", ".join(problems)
    if off is not None or scale is not None:
        return "ok"
    return "motion too large" if motion > config.max_motion_px else "too little texture"


# What to look at when an image fails a test.
ADVICE = {
    "matches behind the cameras": "its cam_to_ego looks the wrong way, or its images belong to another camera",
    "off the epipolar lines": "check its cam_to_ego rotation (axis convention: x right, y down, z forward), "
    "its intrinsics and its capture time",
    "LiDAR scale": "the ego's motion between the keyframes (units, camera_ego_to_world) or the LiDAR's frame is off",
    "implausible motion": "check the units of ego_to_world and camera_ego_to_world (metres) and the timestamps' frames",
}


def problem_line(check: ImageCheck, config: RigCheckConfig = RigCheckConfig()) -> str:
    """One line on a flagged image: what was found (each part of its verdict, `_verdict`), what was
    expected (``config``'s bounds), and what to look at."""
    parts = check.verdict.split(", ")
    found = []
    if "matches behind the cameras" in parts:
        found.append(f"{check.in_front:.0%} of its matches in front of the cameras, expected at least {config.min_in_front:.0%}")
    if "off the epipolar lines" in parts:
        found.append(
            f"matches {check.off_line_px:.2f} px off their epipolar lines (median), expected at most {config.max_off_line_px}"
        )
    if "implausible motion" in parts:
        found.append(f"the poses move it {check.baseline_m:g} m between the keyframes, faster than {config.max_speed_mps:g} m/s")
    if "LiDAR scale" in parts:
        found.append(
            f"its LiDAR agrees best at {check.lidar_scale:.2f} x its depth, expected 1 within {config.max_scale_error:.0%}"
        )
    advice = "; ".join(ADVICE[part] for part in parts if part in ADVICE)
    return f"camera {check.camera}, keyframe {check.keyframe}: {', '.join(found)}: {advice}"


def table_lines(checks: list[ImageCheck]) -> list[str]:
    """The checks as a markdown table."""
    lines = [
        "| camera | keyframe | baseline (m) | expected motion (px) | matches | in front | off the line (px, median) "
        "| within 1 px | LiDAR returns | LiDAR scale | verdict |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for c in checks:
        lines.append(
            f"| {c.camera} | {c.keyframe} | {c.baseline_m:.2f} | {c.motion_px:.0f} | {c.matches} | {_number(c.in_front, '.2f')} "
            f"| {_number(c.off_line_px, '.2f')} | {_number(c.within_1px, '.2f')} | {c.returns} | {_number(c.lidar_scale, '.2f')} "
            f"| {c.verdict} |"
        )
    return lines


def _number(value: float | None, spec: str) -> str:
    return "–" if value is None else format(value, spec)
