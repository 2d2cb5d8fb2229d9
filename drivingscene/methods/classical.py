"""A learning-free baseline: frame pair -> Reconstruction from classical optical flow and the known poses.

What one gets without any network, assembled into the same dynamic Gaussians as the model and
the oracle, so that it is scored and rendered the same way (`score_reconstruction`,
`render.scene`). Everything runs in the local frame of ``PairTensors``:

    guide          = rigid_flows(d0)                          d0: the road plane (ego z = 0) below the
                                                              horizon, ``guide_depth`` (20 m) above it
    total_k        = DIS(I_k, warp(I_{1-k}, guide)) o guide   OpenCV DIS on grey images, per camera, both
                                                              directions, composed with the guide (`dis_flows`)
    depth, static  = triangulate(total, capture poses)        `explain_by_parallax`; candidates: every world
                                                              pixel whose flow is forward/backward consistent
    depth          = fill(depth)                              undetermined pixels: normalised convolution of
                                                              the determined inverse depth in growing windows
                                                              (`fill_depth`); beyond them the road plane below
                                                              the horizon, sky above it
    (again ``passes`` - 1 times, guided by rigid_flows(depth))
    scene flow     = lift(total, depth)                       `lift_scene_flow` on the pixels whose flow is
                                                              off their epipolar line (not explained)
    Gaussians      = one surfel per world pixel                `gaussians_from_pixels` with the pixel's colour
                                                              (``refine`` deconvolution steps: default 0)

Why the guide: on the procedural pairs the ego moves ~4 m between keyframes and the side cameras'
flow is ~100 px at 176x320; DIS alone (its coarse-to-fine search reaches a few tens of pixels)
missed by 90 px (median, static pixels of a validation pair), guided by the road plane and 20 m by
4.7 px. A guided DIS in a flat region returns the guide, which lies on the epipolar line; the
forward/backward check drops most such echoes where the guide is wrong (near walls, pixels that
leave the view): on a validation pair AbsRel of the triangulated pixels 0.38 -> 0.08.

Triangulation is well determined only with parallax: near the epipole (straight ahead and behind
when driving straight), on far surfaces, in flat image regions and on moving objects (their flow
is off the epipolar line) the depth comes from the fill. Sky: a pixel is sky when the road plane
finds no ground within ``far`` along its ray (above the horizon) and no triangulated depth reaches
it through the fill, or when its depth is beyond the model's own sky distance (`sky_mask` with the
depth network's ``ref_focal``, as the model decides); pixels outside ``valid_mask`` are not the
world and make no Gaussian. With the ego standing still nothing triangulates (no baseline) and
the whole depth is the fallback (road plane and sky); pixels whose flow exceeds the lift's
threshold then move.

Defaults chosen on 3 validation pairs (``data/val176``, never the test pairs; intermediate-frame
PSNR, mean): 20.48 dB as set; one pass 20.02; windows up to 16 px instead of 64 18.66 (more
pixels left to the sky); 1 px from the epipolar line instead of 2 20.40 (and 1.6x the dynamic
Gaussians); one colour deconvolution step 20.51 for 2 s more.
"""

from __future__ import annotations

import functools
import os
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace

import cv2
import numpy as np
import torch
from torch import Tensor

from drivingscene.data.frame_pair import FramePair
from drivingscene.data.road_plane import road_plane_depth
from drivingscene.data.tensors import PairTensors, pair_to_tensors, world_cameras
from drivingscene.gaussians.assembly import RAY_EXTENT, extend_along_rays, gaussians_from_pixels
from drivingscene.gaussians.core import Gaussians
from drivingscene.gaussians.recon import Reconstruction
from drivingscene.geometry.flow import forward_backward_consistency, vector_length
from drivingscene.geometry.se3 import rotate_vectors
from drivingscene.methods.oracle import refine_colors, surfel_maps
from drivingscene.models.depth import DepthConfig
from drivingscene.models.lift import LiftConfig, epipolar_geometry, epipolar_tests, lift_scene_flow, sky_mask, texture_along
from drivingscene.models.pipeline import rigid_flows, rigid_flows_and_behind
from drivingscene.render.color_solve import ITERATIONS as COLOR_ITERATIONS
from drivingscene.render.sky import fit_sky_from_pixels

DIS_PRESETS = {
    "ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST,
    "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
    "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM,
}


@dataclass(frozen=True)
class ClassicalConfig:
    """Settings of `classical_reconstruction` (see the module docstring)."""

    # OpenCV DIS preset: "medium" (default), "fast" or "ultrafast" (FACTS.md: 26 / 6 / 4 ms per
    # flow at 352x640).
    preset: str = "medium"
    # DIS is guided by the rigid flow of a first depth guess (`dis_flows`): the road plane below
    # the horizon and ``guide_depth`` metres above it (a typical distance of what lines the road;
    # 10 / 20 / 40 m: 20.21 / 20.48 / 19.66 dB, depth AbsRel 0.41 / 0.48 / 0.73 on validation
    # pairs). Each further pass runs DIS again, guided by the previous pass's depth.
    guide_depth: float = 20.0
    passes: int = 2
    # Fallback depth (metres): the road plane (ego frame z = 0) is used up to this far; a ray that
    # meets no ground within it is above the horizon. Also the farthest triangulated depth kept.
    far: float = 80.0
    # Triangulation (`explain_by_parallax`) and lift (`lift_scene_flow`) thresholds, here in image
    # pixels (the model's are at its networks' input size; 1 px there is 1.8 px at 176x320): on
    # the epipolar line within 2 px, depth taken with >= 4 px of parallax, moving with > 1 px of
    # residual flow.
    lift: LiftConfig = LiftConfig(epipolar_px=2.0)
    # Normalised convolution of inverse depth (`fill_depth`): window radii (pixels at
    # ``reference_width`` image columns, scaled with the width), tried in this order; a pixel
    # takes the first window in which the share of determined pixels reaches ``fill_min_support``.
    # Beyond the last window: the fallback.
    fill_radii: tuple[float, ...] = (2.0, 4.0, 8.0, 16.0, 32.0, 64.0)
    fill_min_support: float = 0.02
    reference_width: int = 320
    # Filled depth below the horizon is at most the road plane's (a surface seen below the horizon
    # is not under the road); triangulated depth is kept as it is.
    clamp_to_road: bool = True
    # Also call sky what the model calls sky (`sky_mask`: depth beyond LiftConfig.sky_depth at
    # the depth network's reference focal length).
    model_sky_rule: bool = True
    # Iterations of the colour solve, as the oracle and the model (`refine_colors`,
    # render/color_solve.py); 0: the pixel colours as they are.
    refine: int = COLOR_ITERATIONS
    # Each Gaussian extended along its view ray, as the model's (`gaussians.assembly.extend_along_rays`); 0: none.
    ray_extent: float = RAY_EXTENT

    def __post_init__(self):
        if self.preset not in DIS_PRESETS:
            raise ValueError(f"ClassicalConfig.preset: expected one of {sorted(DIS_PRESETS)}, found {self.preset!r}")
        if self.passes < 1:
            raise ValueError(f"ClassicalConfig.passes: expected >= 1, found {self.passes}")
        if not 0.0 < self.guide_depth:
            raise ValueError(f"ClassicalConfig.guide_depth: expected > 0 m, found {self.guide_depth}")
        if not self.far > 1.0:
            raise ValueError(f"ClassicalConfig.far: expected > 1 m, found {self.far}")
        if not self.fill_radii or min(self.fill_radii) <= 0:
            raise ValueError(f"ClassicalConfig.fill_radii: expected positive radii, found {self.fill_radii}")
        if not 0.0 < self.fill_min_support <= 1.0:
            raise ValueError(f"ClassicalConfig.fill_min_support: expected a value in (0, 1], found {self.fill_min_support}")
        if self.refine < 0:
            raise ValueError(f"ClassicalConfig.refine: expected >= 0 steps, found {self.refine}")


def dis_flows(images: np.ndarray, preset: str = "medium", guide: np.ndarray | None = None) -> np.ndarray:
    """Optical flow ``[2, V, H, W, 2]`` float32 (pixels) of uint8 images ``[2, V, H, W, 3]``:
    [0] keyframe 0 -> 1 at keyframe-0 pixels, [1] 1 -> 0 (pixel + flow = its position in the
    other keyframe, as ``gt_flow``), by OpenCV's DIS on grey images, camera by camera.

    With a ``guide`` flow ``[2, V, H, W, 2]`` DIS matches each image against the other keyframe
    warped by the guide, and the result r is composed with it: flow(p) = r(p) + guide(p + r(p)).
    DIS's coarse-to-fine search reaches a few tens of pixels; the guide (a rigid flow) takes out
    the rest (rotation, the road, a typical distance), so that DIS only finds the parallax left.

    The images are matched in ``cv2.getNumThreads()`` threads (OpenCV releases the GIL; its own
    parallel loops gain little on images this small): the same flows, in less time."""
    grey = [[cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2GRAY) for image in keyframe] for keyframe in images]
    height, width = images.shape[2:4]
    grid = np.stack(np.meshgrid(np.arange(width, dtype=np.float32), np.arange(height, dtype=np.float32)), -1)
    out = np.zeros((*images.shape[:4], 2), np.float32)
    jobs = [(k, v) for k in (0, 1) for v in range(images.shape[1])]

    def run(part: list[tuple[int, int]]) -> None:
        dis = cv2.DISOpticalFlow_create(DIS_PRESETS[preset])
        for k, v in part:
            if guide is None:
                out[k, v] = dis_calc(dis, grey[k][v], grey[1 - k][v])
                continue
            g = np.ascontiguousarray(guide[k, v], dtype=np.float32)
            warped = cv2.remap(grey[1 - k][v], grid + g, None, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            r = dis_calc(dis, grey[k][v], warped)
            out[k, v] = r + cv2.remap(g, grid + r, None, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)

    in_dis_threads(run, jobs)
    if not np.isfinite(out).all():  # DIS's flow is finite on any image; the check costs 0.1 ms, the copy 5
        np.nan_to_num(out, copy=False, nan=0.0, posinf=0.0, neginf=0.0)
    return out


def in_dis_threads(run: Callable[[list], None], jobs: list) -> None:
    """``run`` over ``jobs`` split into ``cv2.getNumThreads()`` interleaved parts, one per thread
    of the process's DIS pool (`_pool`; ``run`` should spend its time in OpenCV calls, which
    release the GIL), or in this thread where one part is all there is."""
    workers = max(1, min(cv2.getNumThreads(), len(jobs)))
    if workers == 1:
        run(jobs)
    else:
        list(_pool(workers, os.getpid()).map(run, [jobs[i::workers] for i in range(workers)]))


@functools.lru_cache(maxsize=4)
def _pool(workers: int, pid: int) -> ThreadPoolExecutor:
    """One pool of ``workers`` threads per process ``pid``, kept for every later call (starting two
    threads for each pair cost ~4 ms of a 0.5 s reconstruction). Keyed by the process id: a child
    forked after a call inherits the pool object but not its threads, and gets a pool of its own."""
    return ThreadPoolExecutor(workers, thread_name_prefix="dis")


# DIS refuses images with both sides below 12 pixels; smaller ones are padded (replicated edges).
DIS_MIN_SIZE = 16


def dis_calc(dis, first: np.ndarray, second: np.ndarray) -> np.ndarray:
    """DIS flow ``[H, W, 2]`` from grey ``first`` to ``second`` ``[H, W]``, any size."""
    height, width = first.shape
    pad_y, pad_x = max(0, DIS_MIN_SIZE - height), max(0, DIS_MIN_SIZE - width)
    if pad_y or pad_x:
        first, second = (cv2.copyMakeBorder(x, 0, pad_y, 0, pad_x, cv2.BORDER_REPLICATE) for x in (first, second))
    return dis.calc(first, second, None)[:height, :width]


def fill_depth(
    determined: np.ndarray,  # [..., H, W] float32 z-depth, 0 where not determined
    radii: tuple[float, ...],  # pixels
    min_support: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Depth ``[..., H, W]`` with the undetermined pixels filled from the determined ones, and the
    mask of pixels that have a depth (determined or reached by the fill).

    Normalised convolution of inverse depth with square windows: at each radius r in turn, a pixel
    not yet filled takes the depth box(w) / box(w / z) (w = 1 where determined; (2r + 1)^2 windows) if
    box(w), the share of determined pixels in its window, is at least ``min_support``. Inverse
    depth, so that a far and a near neighbour average nearer the near one. Box filters cost the
    same at every radius (running sums), unlike wide Gaussians."""
    flat = determined.reshape(-1, *determined.shape[-2:]).astype(np.float32)
    depth = flat.copy()
    reached = flat > 0
    for i, image in enumerate(flat):
        has = image > 0
        if not has.any():
            continue
        stack = np.stack([np.where(has, 1.0 / np.where(has, image, 1.0), 0.0), has], -1).astype(np.float32)
        filled = has.copy()
        for radius in radii:
            size = 2 * max(1, int(round(radius))) + 1
            inverse, share = cv2.blur(stack, (size, size), borderType=cv2.BORDER_REFLECT).transpose(2, 0, 1)
            new = ~filled & (share >= min_support)
            depth[i][new] = share[new] / np.maximum(inverse[new], 1e-6)
            filled |= new
            if filled.all():
                break
        reached[i] = filled
    return depth.reshape(determined.shape), reached.reshape(determined.shape)


def triangulate(
    total: Tensor, world: Tensor, batch: PairTensors, lift: LiftConfig, *, with_parallax: bool = False
) -> tuple[Tensor, Tensor] | tuple[Tensor, Tensor, Tensor]:
    """Triangulated depth ``[2, V, H, W]`` (0 where not determined) and the explained mask:
    `explain_by_parallax`'s test with every world pixel whose flow is forward/backward consistent
    as a candidate, the determined pixels at their triangulated depth. ``with_parallax``: also
    each pixel's parallax (pixels, `epipolar_geometry`)."""
    # Occluded pixels and those that leave the view have no match: DIS gives them a flow anyway
    # (often the guide's, which lies on the epipolar line), which the other direction contradicts.
    candidates = world & torch.stack([forward_backward_consistency(total[k], total[1 - k]) for k in (0, 1)])
    c2l = batch.cam_to_local.float()
    depths, explained_all, parallaxes = [], [], []
    for k in (0, 1):
        rel = torch.linalg.inv(c2l[1 - k]) @ c2l[k]
        z, off_line, parallax, valid = epipolar_geometry(total[k].float(), batch.intrinsics.float(), rel)
        parallax_px = vector_length(parallax)
        explained, determined = epipolar_tests(z, off_line, parallax_px, valid, candidates[k], lift)
        if lift.epipolar_min_texture > 0 and determined.any():
            determined &= texture_along(batch.images[k].float(), parallax, 1.0) >= lift.epipolar_min_texture
        depths.append(torch.where(determined, z, torch.zeros_like(z)))
        explained_all.append(explained)
        parallaxes.append(parallax_px)
    depth, explained = torch.stack(depths), torch.stack(explained_all)
    return (depth, explained, torch.stack(parallaxes)) if with_parallax else (depth, explained)


def _depth_and_sky(
    triangulated: Tensor, road: Tensor, batch: PairTensors, world: Tensor, config: ClassicalConfig
) -> tuple[Tensor, Tensor, Tensor]:
    """Depth ``[2, V, H, W]`` (filled; the road plane ``road`` elsewhere), sky and determined
    masks (see module)."""
    no_ground = road >= config.far
    scale = road.shape[-1] / config.reference_width
    determined = triangulated > 0
    filled, reached = fill_depth(triangulated.numpy(), tuple(r * scale for r in config.fill_radii), config.fill_min_support)
    filled, reached = torch.from_numpy(filled), torch.from_numpy(reached)
    if config.clamp_to_road:
        filled = torch.where(determined | no_ground, filled, torch.minimum(filled, road))
    depth = torch.where(reached, filled, road)
    depth = torch.where(torch.isfinite(depth) & (depth > 0), depth, road)
    sky = no_ground & ~reached
    if config.model_sky_rule:
        sky |= sky_mask(depth, batch.intrinsics, DepthConfig().ref_focal, config.lift)
    return depth.float(), sky & world, determined


def _estimate_depth(
    pair: FramePair, batch: PairTensors, world: Tensor, lift: LiftConfig, config: ClassicalConfig, timings: dict
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Guided DIS, triangulation and fill, ``config.passes`` times: the total flow
    ``[2, V, H, W, 2]``, depth ``[2, V, H, W]``, and the sky, determined and explained masks."""
    road = torch.from_numpy(road_plane_depth(pair, far=config.far))
    guide = torch.where(road >= config.far, torch.full_like(road, config.guide_depth), road)
    timings.update(flow_s=0.0, parallax_s=0.0, fill_s=0.0)
    for _ in range(config.passes):
        t0 = time.perf_counter()
        rigid = rigid_flows(guide, batch)
        total = torch.from_numpy(dis_flows(pair.images, config.preset, rigid.numpy()))
        t1 = time.perf_counter()
        triangulated, explained = triangulate(total, world, batch, lift)
        t2 = time.perf_counter()
        depth, sky, determined = _depth_and_sky(triangulated, road, batch, world, config)
        guide = torch.where(sky, torch.full_like(depth, config.far), depth)
        timings["flow_s"] += t1 - t0
        timings["parallax_s"] += t2 - t1
        timings["fill_s"] += time.perf_counter() - t2
    return total, depth, sky, determined, explained


@torch.no_grad()
def classical_reconstruction(pair: FramePair, config: ClassicalConfig = ClassicalConfig()) -> Reconstruction:
    """Dynamic Gaussians of both keyframes (world frame) and per-camera maps from DIS flow,
    triangulation and fill (no network; see the module docstring), with timings in ``meta``."""
    timings = {}
    start = time.perf_counter()
    batch = pair_to_tensors(pair, with_gt=False, with_eval=False)
    world = torch.ones(2, pair.num_views, *pair.image_size, dtype=torch.bool)
    if batch.valid_mask is not None:
        world = world & batch.valid_mask
    lift = config.lift
    if lift.epipolar_far > config.far:
        lift = replace(lift, epipolar_far=config.far)
    total, depth, sky_pixels, determined, explained = _estimate_depth(pair, batch, world, lift, config, timings)

    t0 = time.perf_counter()
    # Not the world (ego body) is treated like sky from here on, as in the model, except in the sky fit.
    sky = sky_pixels | ~world
    rigid, behind = rigid_flows_and_behind(depth, batch)
    rigid = torch.where(determined[..., None], total, rigid)  # as `explain_by_parallax` sets it
    residual = total - rigid
    # Explained pixels are static; the others move where their residual is large and consistent.
    scene_flow, _ = lift_scene_flow(depth, total, residual, sky | explained, batch, lift, rigid=rigid, behind=behind)
    timings["lift_s"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    gaussians, sky_sh = _assemble(batch, depth, sky, sky_pixels, scene_flow, config.refine, config.ray_extent)
    timings["assembly_s"] = time.perf_counter() - t0
    timings["total_s"] = time.perf_counter() - start
    sky_np = sky.numpy()
    return Reconstruction.from_pair(
        pair,
        gaussians,
        sky_sh=sky_sh,
        depth=np.where(sky_np, 0.0, depth.numpy()).astype(np.float32),
        rigid_flow=np.where(sky_np[..., None], 0.0, rigid.numpy()).astype(np.float32),
        residual_flow=np.where(sky_np[..., None], 0.0, residual.numpy()).astype(np.float32),
        meta={
            "method": "classical-dis",
            "preset": config.preset,
            "passes": config.passes,
            "refine": config.refine,
            "determined_share": round(float(determined[world].float().mean()) if world.any() else 0.0, 4),
            "timings": {k: round(v, 4) for k, v in timings.items()},
        },
    )


def _assemble(
    batch: PairTensors, depth: Tensor, sky: Tensor, sky_pixels: Tensor, scene_flow: Tensor, refine: int, ray_extent: float
) -> tuple[Gaussians, Tensor]:
    """Gaussians of both keyframes in the world frame, one per non-sky world pixel with its colour
    (after ``refine`` iterations of the colour solve) and extended along its view ray by
    ``ray_extent``, and the sky SH fitted to ``sky_pixels``."""
    num_views = batch.num_views
    c2w = world_cameras(batch)  # [2, V, 4, 4]
    sky_sh = fit_sky_from_pixels(batch.images, sky_pixels, c2w, batch.intrinsics)
    colors = batch.images.permute(0, 1, 3, 4, 2).flatten(0, 1)  # [2V, H, W, 3]
    depths, intrinsics = depth.flatten(0, 1), batch.intrinsics.repeat(2, 1, 1)
    quats, log_scales = surfel_maps(depths, intrinsics)
    colors = refine_colors(depths, intrinsics, colors, ~sky.flatten(0, 1), refine, (quats, log_scales))
    quats, log_scales = extend_along_rays(depths, intrinsics, quats, log_scales, ray_extent)
    flows = rotate_vectors(batch.local_to_world[:3, :3].float(), scene_flow.float())
    gaussians = gaussians_from_pixels(
        depths,
        intrinsics,
        c2w.flatten(0, 1).float(),
        colors,
        quats=quats,
        log_scales=log_scales,
        footprints=None,
        keyframe=torch.arange(2).repeat_interleave(num_views),
        camera_ids=torch.arange(num_views).repeat(2),
        flows=flows.flatten(0, 1),
        valid=~sky.flatten(0, 1),
    )
    return gaussians, sky_sh
