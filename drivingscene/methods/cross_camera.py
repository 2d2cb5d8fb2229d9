"""Depth from matching overlapping cameras of one keyframe (stereo across the rig).

The matching of `matched_depth` triangulates along the ego's motion between the keyframes: where
that motion gives no parallax (around each camera's focus of expansion, and everywhere when the ego
stands still) it determines nothing. Neighbouring cameras of a surround rig see the same surfaces
from mounts a fraction of a metre to a few metres apart, at the same instant: their overlap is a
stereo pair whose baseline the extrinsics give, whatever the ego does.

For each keyframe and each ordered pair of cameras (a, b) whose views overlap under a guide depth
(at least ``min_overlap`` of a's world pixels land inside b's world pixels):

1. the guide's flow from a to b (a's pixel, lifted to the guide depth, projected into b) warps b's
   grey image onto a's, over the bounding box of the overlap only, and the warped image takes a's
   mean and spread there (the cameras expose independently);
2. OpenCV's DIS matches a against it; the residual composed with the guide is a's flow into b;
3. a pixel is determined where its match is undone by b's match back into a (within
   ``consistency_px``), lies within the epipolar thresholds of `LiftConfig` (off the line at most
   ``epipolar_px``, at least ``epipolar_min_parallax`` pixels from the point at infinity, depth in
   [``epipolar_near``, ``epipolar_far``]) and lands on a world pixel of b; its depth is the
   least-squares point along its ray (`rig_triangulate`). Of several partners, the one with the
   most parallax.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import torch
from torch import Tensor

from drivingscene import kernels
from drivingscene.data.tensors import PairTensors
from drivingscene.methods.classical import DIS_PRESETS, dis_calc, in_dis_threads
from drivingscene.models.lift import LiftConfig


@dataclass(frozen=True)
class CrossCameraConfig:
    """Settings of `cross_camera_depth` (see the module docstring)."""

    preset: str = "medium"
    # A camera pair is matched where at least this share of the first camera's world pixels lands
    # on world pixels of the second under the guide depth.
    min_overlap: float = 0.02
    # Pixels around the overlap's bounding box that are matched too (DIS's patches need context).
    margin: int = 8
    # A match is kept where the way back lands within this many pixels of where it started.
    consistency_px: float = 1.0

    def __post_init__(self):
        if self.preset not in DIS_PRESETS:
            raise ValueError(f"CrossCameraConfig.preset: expected one of {sorted(DIS_PRESETS)}, found {self.preset!r}")
        if not 0.0 < self.min_overlap <= 1.0:
            raise ValueError(f"CrossCameraConfig.min_overlap: expected a share in (0, 1], found {self.min_overlap}")
        if self.margin < 0:
            raise ValueError(f"CrossCameraConfig.margin: expected >= 0 pixels, found {self.margin}")
        if not self.consistency_px > 0.0:
            raise ValueError(f"CrossCameraConfig.consistency_px: expected > 0 pixels, found {self.consistency_px}")


# A point must lie this far (metres, z-depth) in front of the camera that sees it.
NEAR_Z = 0.1


def _pixel_rays(intrinsics: np.ndarray, height: int, width: int, step: int = 1) -> np.ndarray:
    """Each camera's pixel rays ``[V, h, w, 3]`` float32 (z = 1) at every ``step``-th row and column."""
    u, v = np.meshgrid(np.arange(0, width, step, dtype=np.float32), np.arange(0, height, step, dtype=np.float32))
    pixels = np.stack([u, v, np.ones_like(u)], -1)
    return pixels @ np.swapaxes(np.linalg.inv(intrinsics), -1, -2).astype(np.float32)[:, None]


def _project(points: np.ndarray, k_b: np.ndarray, a_to_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points ``[..., 3]`` in camera a's axes projected into camera b: their positions ``[..., 2]``
    (pixels of b) and b's z-depth of them ``[...]``. ``k_b`` ``[3, 3]``, ``a_to_b`` ``[4, 4]``."""
    there = points @ (k_b @ a_to_b[:3, :3]).T.astype(np.float32) + (k_b @ a_to_b[:3, 3]).astype(np.float32)
    z = there[..., 2]
    return there[..., :2] / np.maximum(z, NEAR_Z)[..., None], z


def _lands(uv: np.ndarray, z: np.ndarray, world_b: np.ndarray) -> np.ndarray:
    """Projected points (`_project`) in front of b that land on b's world pixels ``[H, W]``."""
    height, width = world_b.shape
    col, row = np.rint(uv[..., 0]), np.rint(uv[..., 1])
    inside = (z > NEAR_Z) & (col >= 0) & (col < width) & (row >= 0) & (row < height)
    out = np.zeros(inside.shape, bool)
    out[inside] = world_b[row[inside].astype(np.int64), col[inside].astype(np.int64)]
    return out


def rig_triangulate(
    end: np.ndarray,  # [N, 2] the match in camera b (pixels of b)
    start: np.ndarray,  # [N, 2] the pixel in camera a
    k_a: np.ndarray,  # [3, 3]
    k_b: np.ndarray,  # [3, 3]
    a_to_b: np.ndarray,  # [4, 4]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Two-camera triangulation with each camera's own intrinsics: the z-depth in a ``[N]`` of the
    point along a's ray whose image in b is nearest ``end`` (least squares over both image axes,
    as `pipeline.epipolar_geometry` for one camera at two times), that image's distance from
    ``end`` (pixels of b; infinite where the point is not in front of both cameras) and its
    distance from the image of the ray's point at infinite depth (the parallax, pixels of b)."""
    rotation = (a_to_b[:3, :3] @ np.linalg.inv(k_a)).astype(np.float32)
    t = a_to_b[:3, 3].astype(np.float32)
    ray = start @ rotation[:, :2].T + rotation[:, 2]  # a's ray in b's axes (z = 1 in a)
    k_b_inv = np.linalg.inv(k_b).astype(np.float32)
    x = end @ k_b_inv[:2, :2].T + k_b_inv[:2, 2]  # the end point, normalised (K's last row is 0 0 1)
    coef = ray[:, :2] - x * ray[:, 2:3]
    rhs = x * t[2] - t[:2]
    z = (coef * rhs).sum(1) / np.maximum(np.square(coef).sum(1), 1e-12)
    point = z[:, None] * ray + t
    k_b = k_b.astype(np.float32)
    proj = point @ k_b.T
    proj = proj[:, :2] / np.maximum(proj[:, 2:3], 1e-6)
    at_infinity = ray @ k_b.T
    at_infinity = at_infinity[:, :2] / np.maximum(at_infinity[:, 2:3], 1e-6)
    off_line = np.hypot(*(proj - end).T)
    parallax = np.hypot(*(proj - at_infinity).T)
    ok = (point[:, 2] > NEAR_Z) & (ray[:, 2] > 0) & np.isfinite(z)
    return np.where(ok, z, 0.0), np.where(ok, off_line, np.inf), np.where(ok, parallax, 0.0)


@dataclass
class _Job:
    key: int
    a: int
    b: int
    a_to_b: np.ndarray  # [4, 4] float64
    box: tuple[int, int, int, int]  # y0, y1, x0, x1 in a
    grid: np.ndarray  # [h, w, 2] float32: the box's pixels (a)
    guide: np.ndarray  # [h, w, 2] float32: where the guide takes them in b (pixels of b)
    overlap: np.ndarray  # [h, w] uint8: 1 where that is one of b's world pixels
    end: np.ndarray | None = None  # [h, w, 2] float32: where the match lands in b (pixels of b)


def _normalised(image: np.ndarray, like: np.ndarray, where: np.ndarray) -> np.ndarray:
    """``image`` (uint8) with ``like``'s mean and standard deviation over ``where`` (uint8 mask)."""
    (mean_x,), (std_x,) = cv2.meanStdDev(image, mask=where)
    (mean_y,), (std_y,) = cv2.meanStdDev(like, mask=where)
    gain = float(std_y[0]) / max(float(std_x[0]), 1.0)
    return cv2.convertScaleAbs(image, alpha=gain, beta=float(mean_y[0] - mean_x[0] * gain))


def _box_grid(box: tuple[int, int, int, int]) -> np.ndarray:
    y0, y1, x0, x1 = box
    return np.stack(np.meshgrid(np.arange(x0, x1, dtype=np.float32), np.arange(y0, y1, dtype=np.float32)), -1)


# The overlap test runs on every OVERLAP_STEP-th row and column.
OVERLAP_STEP = 8


def _guide(
    depth: np.ndarray, grid: np.ndarray, k_a: np.ndarray, k_b: np.ndarray, a_to_b: np.ndarray, k_a_inv: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Where a box of camera a's pixels (``grid`` ``[h, w, 2]``, at z-depth ``depth``) land in b
    ``[h, w, 2]`` and b's z-depth of them: the compiled rigid flow (`kernels.rigid_flow_dense`,
    a's principal point moved to the box's corner) where it is available, else numpy."""
    shifted = k_a.copy()
    shifted[:2, 2] -= grid[0, 0]
    tensors = [torch.from_numpy(np.ascontiguousarray(x, np.float32))[None] for x in (depth, shifted, a_to_b, k_b)]
    if kernels.available(kernels.rigid_flow_dense, "auto", *tensors):
        flow, z = kernels.rigid_flow_dense(*tensors)
        return flow[0].numpy() + (grid - grid[0, 0]), z[0].numpy()
    rays = grid @ k_a_inv[:, :2].T.astype(np.float32) + k_a_inv[:, 2].astype(np.float32)
    return _project(rays * depth[..., None], k_b, a_to_b)


def _jobs(
    depth: np.ndarray, world: np.ndarray, intrinsics: np.ndarray, cam_to_local: np.ndarray, config: CrossCameraConfig
) -> list[_Job]:
    """The camera pairs to match: those whose overlap under the guide depth reaches
    ``min_overlap`` (tested on every ``OVERLAP_STEP``-th pixel, all pairs at once), with where
    the guide takes the pixels of the bounding box of the overlap."""
    num_views, height, width = depth.shape[1:]
    step = OVERLAP_STEP
    coarse_rays = _pixel_rays(intrinsics, height, width, step)  # [V, h, w, 3]
    k_inv = np.linalg.inv(intrinsics).astype(np.float32)
    jobs = []
    for k in (0, 1):
        a_to_b = np.linalg.inv(cam_to_local[k])[None] @ cam_to_local[k][:, None]  # [a, b, 4, 4]
        to_pixels = intrinsics[None] @ a_to_b[..., :3, :]  # [a, b, 3, 4]: K_b [R | t]
        coarse_world = world[k, :, ::step, ::step]
        points = coarse_rays * depth[k, :, ::step, ::step, None]
        there = points.reshape(num_views, 1, -1, 3) @ np.swapaxes(to_pixels[..., :3], -1, -2).astype(np.float32)
        there = (there + to_pixels[:, :, None, :, 3].astype(np.float32)).reshape(num_views, num_views, *points.shape[1:])
        z = there[..., 2]
        col = np.rint(there[..., 0] / np.maximum(z, NEAR_Z))
        row = np.rint(there[..., 1] / np.maximum(z, NEAR_Z))
        inside = (z > NEAR_Z) & (col >= 0) & (col < width) & (row >= 0) & (row < height) & coarse_world[:, None]
        partner = np.broadcast_to(np.arange(num_views)[None, :, None, None], inside.shape)
        inside[inside] = world[k][partner[inside], row[inside].astype(np.int64), col[inside].astype(np.int64)]
        counts = coarse_world.reshape(num_views, -1).sum(1)
        for a in range(num_views):
            for b in range(num_views):
                overlap = inside[a, b]
                if b == a or counts[a] == 0 or overlap.sum() < config.min_overlap * counts[a]:
                    continue
                rows, cols = np.nonzero(overlap)
                m = config.margin + step
                y0, y1 = max(int(rows.min()) * step - m, 0), min(int(rows.max()) * step + m + 1, height)
                x0, x1 = max(int(cols.min()) * step - m, 0), min(int(cols.max()) * step + m + 1, width)
                box = (y0, y1, x0, x1)
                grid = _box_grid(box)
                uv, z = _guide(depth[k, a, y0:y1, x0:x1], grid, intrinsics[a], intrinsics[b], a_to_b[a, b], k_inv[a])
                lands = _lands(uv, z, world[k, b]) & world[k, a, y0:y1, x0:x1]
                jobs.append(_Job(k, a, b, a_to_b[a, b], box, grid, np.ascontiguousarray(uv), lands.astype(np.uint8)))
    return jobs


def _match(jobs: list[_Job], images: np.ndarray, preset: str) -> None:
    """Each job's match (`_Job.end`) by DIS against the partner warped by the guide, in the DIS
    threads of `classical.dis_flows` (OpenCV calls only: they release the GIL)."""
    grey = [[cv2.cvtColor(np.ascontiguousarray(im), cv2.COLOR_RGB2GRAY) for im in keyframe] for keyframe in images]

    def run(part: list[_Job]) -> None:
        dis = cv2.DISOpticalFlow_create(DIS_PRESETS[preset])
        for job in part:
            y0, y1, x0, x1 = job.box
            first = grey[job.key][job.a][y0:y1, x0:x1]
            warped = cv2.remap(grey[job.key][job.b], job.guide, None, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            r = dis_calc(dis, np.ascontiguousarray(first), _normalised(warped, first, job.overlap))
            # the residual r composed with the guide: p + r(p) lands at guide(p + r(p)) in b
            local = cv2.add(job.grid, r) - np.array([x0, y0], np.float32)
            job.end = cv2.remap(job.guide, local, None, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)

    in_dis_threads(run, jobs)


def _geometry(job: _Job, intrinsics: np.ndarray) -> np.ndarray:
    """`kernels.rig_stereo`'s camera pair: M = R K_a^-1, t, K_b, K_b^-1, float32 ``[30]``."""
    k_b = intrinsics[job.b]
    m = job.a_to_b[:3, :3] @ np.linalg.inv(intrinsics[job.a])
    return np.concatenate([m.ravel(), job.a_to_b[:3, 3], k_b.ravel(), np.linalg.inv(k_b).ravel()]).astype(np.float32)


def _stereo_numpy(
    job: _Job,
    back: _Job,
    world_a: np.ndarray,
    world_b: np.ndarray,
    intrinsics: np.ndarray,
    lift: LiftConfig,
    config: CrossCameraConfig,
) -> tuple[np.ndarray, np.ndarray]:
    """The reference path of `kernels.rig_stereo`: z-depth and parallax ``[h, w]`` of the job's
    box, 0 where not determined."""
    end = job.end
    z_out, parallax_out = np.zeros(end.shape[:2], np.float32), np.zeros(end.shape[:2], np.float32)
    height, width = world_b.shape
    with np.errstate(invalid="ignore"):
        col, row = np.rint(end[..., 0]), np.rint(end[..., 1])
        onto = (col >= 0) & (col < width) & (row >= 0) & (row < height) & world_a
    onto[onto] = world_b[row[onto].astype(np.int64), col[onto].astype(np.int64)]
    by0, bx0 = back.box[0], back.box[2]
    hb, wb = back.end.shape[:2]
    cx, cy = col - bx0, row - by0
    onto &= (cx >= 0) & (cx < wb) & (cy >= 0) & (cy < hb)
    rows, cols = np.nonzero(onto)
    returned = back.end[cy[rows, cols].astype(np.int64), cx[rows, cols].astype(np.int64)]
    start = job.grid[rows, cols]
    consistent = np.square(returned - start).sum(1) <= config.consistency_px**2
    rows, cols, start = rows[consistent], cols[consistent], start[consistent]
    z, off_line, parallax = rig_triangulate(end[rows, cols], start, intrinsics[job.a], intrinsics[job.b], job.a_to_b)
    ok = (off_line <= lift.epipolar_px) & (parallax >= lift.epipolar_min_parallax)
    ok &= (z >= lift.epipolar_near) & (z <= lift.epipolar_far)
    z_out[rows[ok], cols[ok]] = z[ok]
    parallax_out[rows[ok], cols[ok]] = parallax[ok]
    return z_out, parallax_out


def _stereo(
    job: _Job,
    back: _Job,
    world_a: np.ndarray,
    world_b: np.ndarray,
    intrinsics: np.ndarray,
    lift: LiftConfig,
    config: CrossCameraConfig,
    backend: str,
) -> tuple[np.ndarray, np.ndarray]:
    """`kernels.rig_stereo` where it is available, else `_stereo_numpy`."""
    tensors = (torch.from_numpy(job.end), torch.from_numpy(back.end))
    if kernels.available(kernels.rig_stereo, backend, *tensors):
        z, parallax = kernels.rig_stereo(
            *tensors,
            torch.from_numpy(world_a),
            torch.from_numpy(world_b),
            torch.from_numpy(_geometry(job, intrinsics)),
            job.box[2],
            job.box[0],
            back.box[2],
            back.box[0],
            config.consistency_px,
            lift.epipolar_px,
            lift.epipolar_min_parallax,
            lift.epipolar_near,
            lift.epipolar_far,
            NEAR_Z,
        )
        return z.numpy(), parallax.numpy()
    return _stereo_numpy(job, back, world_a, world_b, intrinsics, lift, config)


def cross_camera_depth(
    depth: Tensor,  # [2, V, H, W] guide z-depth (metres)
    keep: Tensor,  # [2, V, H, W] bool: world pixels (not sky, not the ego body)
    images: np.ndarray,  # [2, V, H, W, 3] uint8
    batch: PairTensors,
    lift: LiftConfig,
    config: CrossCameraConfig = CrossCameraConfig(),
    backend: str = "auto",
) -> tuple[Tensor, Tensor, int]:
    """Triangulated z-depth ``[2, V, H, W]`` float32 (0 where not determined), each determined
    pixel's parallax (pixels of the partner camera; 0 elsewhere), and how many ordered camera
    pairs were matched. CPU tensors; see the module docstring. ``backend``: the checks and the
    triangulation in one compiled pass per pixel (`drivingscene.kernels.rig_stereo`; "auto" or
    "cpp") or in numpy ("torch": the reference path, `_stereo_numpy`)."""
    d = depth.detach().float().cpu().numpy()
    world = keep.cpu().numpy()
    intrinsics = batch.intrinsics.double().cpu().numpy()
    jobs = _jobs(d, world, intrinsics, batch.cam_to_local.double().cpu().numpy(), config)
    _match(jobs, images, config.preset)
    by_pair = {(job.key, job.a, job.b): job for job in jobs}
    out, best = np.zeros_like(d), np.zeros_like(d)
    for job in jobs:
        back = by_pair.get((job.key, job.b, job.a))
        if back is None:  # b's overlap with a fell short of min_overlap: no way back to check
            continue
        y0, y1, x0, x1 = job.box
        z, parallax = _stereo(
            job, back, world[job.key, job.a, y0:y1, x0:x1], world[job.key, job.b], intrinsics, lift, config, backend
        )
        # of several partners, the one with the most parallax
        better = parallax > best[job.key, job.a, y0:y1, x0:x1]
        out[job.key, job.a, y0:y1, x0:x1][better] = z[better]
        best[job.key, job.a, y0:y1, x0:x1][better] = parallax[better]
    return torch.from_numpy(out), torch.from_numpy(best), len(jobs)
