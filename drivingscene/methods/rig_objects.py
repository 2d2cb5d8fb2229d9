"""Moving objects searched across the rig (issue 46, an option of the inference).

The tracking of `methods.object_motion` matches an object within one camera. It cannot follow an
object that leaves that camera between the keyframes, or one so close that the rigid flow itself
leaves the image (the demo's bus fills CAM_BACK_LEFT at t = 0 and is in CAM_BACK at t = 1): such
pixels are "outside" for the rigid flow and stay static, and the in-between frame draws them as a
ghost where they stood. Here a blob of such pixels is searched as one rigid translation of its
surface, scored in every camera of the other keyframe:

    blob      = components of (rigid flow's cost > threshold, or its rigid flow leaves the image),
                not sky, not moving already, at least ``min_pixels``
    X         = the blob's pixels lifted with the depth at keyframe k (local frame), sampled
    cost(T)   = mean over X of the least |I_k(p) - I_o,c(proj_c(X + T))| (mean RGB, box-filtered
                images) over the cameras c of the other keyframe that see X + T (in front of the
                camera and not hidden behind its depth there, ``seen``); ``unseen`` where none does
    T*        = argmin of cost over translations on the ground plane (``radius``, ``step``), then
                refined twice at a quarter of the step; a blob the other keyframe's cameras explain
                standing still (cost(0) <= ``still_cost``) is not searched
    accepted  = cost(T*) <= ``ratio`` cost(0); X + T* seen by ``min_seen``; |T*| >= ``min_motion``;
                unique: no translation ``unique_m`` or more away within ``unique`` of it (flat road
                matches flat road anywhere), and no static surface at another depth along the same
                rays (``depth_scales``) either (parallax before motion)
    pixels    = the blob's pixels whose own cost under T* is below ``threshold`` and below their cost
                standing still (a blob also holds the background the object uncovers)
    landing   = where those pixels land in the other keyframe's cameras (at that camera's depth):
                they move back by -T*, so that both keyframes' copies of the object agree

The translation is what the Gaussians follow (scene flow, local frame): nothing is asked of the
optical flow within one camera. Static surfaces whose rigid flow leaves the image are scored with
T = 0 in the cameras that do see them at the other keyframe (``still_cost``). Measured in
docs/moving-objects.md (*Across the rig*): the moving pixels gain where it finds an object, but
static surfaces whose depth is off are moved too (a translation along the ego's path reads like a
depth error) and it costs about 2 s per pair: off by default.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import torch

from drivingscene.methods.object_costs import pixel_grid, warp_cost


@dataclass(frozen=True)
class RigObjectConfig:
    threshold: float = 0.08  # the rigid flow's box-averaged cost above which a pixel is a candidate
    box: int = 5
    min_pixels: int = 600  # the smallest blob searched (pixels at the image's size)
    samples: int = 256  # blob pixels the search scores each translation with
    # > 0: only blobs at least this share of whose pixels the rigid flow carries out of the image
    # (what the tracking within one camera cannot follow); 0: every blob
    leaving: float = 0.0
    # A blob whose pixels the cameras of the other keyframe already explain standing still (their
    # mean cost at most this) is not searched: the rigid flow left the image, the rig did not
    still_cost: float = 0.05
    radius: float = 16.0  # metres: the translations searched, on the ground plane
    step: float = 1.0  # metres: the coarse grid's step; refined twice at a quarter of it (6 cm)
    depth_tol: float = 0.15
    # Which cameras see a point: "front", those where it lies no more than ``depth_tol`` behind the
    # camera's depth there (not hidden: it may stand in front of what the camera saw); "depth", only
    # those where it lies within ``depth_tol`` of that depth (on the surface the camera saw)
    seen: str = "front"
    unseen: float = 0.15  # the cost of a point no camera sees (mean RGB difference in [0, 1])
    ratio: float = 0.7
    min_seen: float = 0.5
    min_motion: float = 1.0  # metres
    unique: float = 0.85
    unique_m: float = 2.0
    # Parallax before motion: the blob standing still at its depth times each of these scales (along
    # the rays of its camera); an object is refused where one of them explains it within ``unique``
    # of the best translation (a static surface whose depth is off reads as a translation along the
    # ego's path). Empty: off.
    depth_scales: tuple[float, ...] = (0.5, 0.6, 0.7, 0.8, 0.9, 1.1, 1.25, 1.4, 1.6, 1.8, 2.0, 2.5)

    def __post_init__(self):
        if self.seen not in ("front", "depth"):
            raise ValueError(f"RigObjectConfig.seen: expected 'front' or 'depth', found {self.seen!r}")
        if not 0 <= self.leaving <= 1:
            raise ValueError(f"RigObjectConfig.leaving: expected a share in [0, 1], found {self.leaving}")
        if min(self.min_pixels, self.samples, self.box) < 1 or not 0 < self.step <= self.radius:
            raise ValueError(f"RigObjectConfig: expected positive sizes and 0 < step <= radius, found {self}")


@dataclass(frozen=True)
class RigObject:
    keyframe: int
    camera: int
    pixels: np.ndarray  # [H, W] bool at its keyframe
    translation: np.ndarray  # [3] local frame, metres, keyframe -> the other
    landing: np.ndarray  # [V, H, W] bool: its pixels at the other keyframe (they move by -translation)
    cost: float
    static_cost: float


def _lift(depth: np.ndarray, intrinsics: np.ndarray, cam_to_local: np.ndarray, ys: np.ndarray, xs: np.ndarray) -> np.ndarray:
    """Local-frame points ``[N, 3]`` of pixels (xs, ys) at ``depth`` (z, pixel centres at integers,
    as `geometry.camera.unproject`)."""
    d = depth[ys, xs].astype(np.float64)
    rays = np.linalg.inv(intrinsics.astype(np.float64)) @ np.stack([xs, ys, np.ones_like(xs)], 0).astype(np.float64)
    cam = rays * d
    return cam.T @ cam_to_local[:3, :3].T + cam_to_local[:3, 3]


class _Views:
    """The other keyframe's cameras: projection, depth and box-filtered images."""

    def __init__(self, images, depth, intrinsics, cam_to_local, config: RigObjectConfig):
        self.images, self.depth, self.k, self.config = images, depth, intrinsics.astype(np.float32), config
        self.local_to_cam = np.linalg.inv(cam_to_local.astype(np.float64)).astype(np.float32)
        self.height, self.width = depth.shape[1:]

    def project(self, points: np.ndarray, c: int) -> tuple[np.ndarray, np.ndarray]:
        """Camera ``c``'s pixel coordinates ``[..., 2]`` and z-depth ``[...]`` of ``points`` ``[..., 3]``."""
        q = points @ self.local_to_cam[c, :3, :3].T + self.local_to_cam[c, :3, 3]
        z = q[..., 2]
        return (q @ self.k[c].T)[..., :2] / np.maximum(z, 1e-6)[..., None], z

    def pixel(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The nearest pixel (row, column) of coordinates ``uv`` ``[..., 2]``, clamped to the image."""
        col = np.clip(np.rint(uv[..., 0]), 0, self.width - 1).astype(np.int64)
        row = np.clip(np.rint(uv[..., 1]), 0, self.height - 1).astype(np.int64)
        return row, col

    def costs(self, points: np.ndarray, colours: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per point of ``points`` ``[..., N, 3]`` the least colour difference over the cameras that
        see it at their depth (inf where none), and which camera that is (-1 where none)."""
        best = np.full(points.shape[:-1], np.inf)
        which = np.full(points.shape[:-1], -1, np.int64)
        for c in range(len(self.images)):
            uv, z = self.project(points, c)
            inside = (z > 0.3) & (uv[..., 0] > -0.5) & (uv[..., 0] < self.width - 0.5) & (uv[..., 1] > -0.5)
            inside &= uv[..., 1] < self.height - 0.5
            if not inside.any():
                continue
            row, col = self.pixel(uv)
            there = self.depth[c][row, col]
            if self.config.seen == "depth":
                seen = inside & (there > 0) & (np.abs(z - there) < self.config.depth_tol * z)
            else:  # not behind what that camera sees
                seen = inside & (there > 0) & (z < (1 + self.config.depth_tol) * there)
            sampled = _sample(self.images[c], uv).reshape(*points.shape[:-1], 3)
            error = np.abs(sampled - colours).mean(-1)
            better = seen & (error < best)
            best = np.where(better, error, best)
            which = np.where(better, c, which)
        return best, which

    def mean_cost(self, points: np.ndarray, colours: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        best, _ = self.costs(points, colours)
        seen = np.isfinite(best)
        return np.where(seen, best, self.config.unseen).mean(-1), seen.mean(-1)


def _sample(image: np.ndarray, uv: np.ndarray, row: int = 4096) -> np.ndarray:
    """``image`` ``[H, W, 3]`` sampled bilinearly at ``uv`` ``[..., 2]`` (border replicated):
    ``[n, 3]`` for the n points (OpenCV's remap, whose maps hold fewer than 32767 rows, over
    rows of ``row`` points)."""
    flat = uv.reshape(-1, 2).astype(np.float32)
    n = len(flat)
    padded = np.zeros((-(-n // row) * row, 2), np.float32)
    padded[:n] = flat
    maps = padded.reshape(-1, row, 2)
    out = cv2.remap(image, maps[..., 0], maps[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return out.reshape(-1, 3)[:n]


def _plane_axes(cam_to_local: np.ndarray, up: np.ndarray) -> np.ndarray:
    """Two unit vectors ``[2, 3]`` spanning the ground plane (normal ``up``, local frame)."""
    up = up / np.linalg.norm(up)
    ahead = cam_to_local[0, :3, 2] - up * (cam_to_local[0, :3, 2] @ up)  # the first camera's view, levelled
    ahead /= np.linalg.norm(ahead)
    return np.stack([ahead, np.cross(up, ahead)])


def _search(views: _Views, points, colours, axes, config: RigObjectConfig):
    """The best translation on the ground plane, its cost and seen share, and the best cost at
    least ``unique_m`` away from it: a grid of ``step`` over ``radius``, then two finer grids
    (a quarter of the step each time) around the best."""
    n = int(round(config.radius / config.step))
    a = np.arange(-n, n + 1) * config.step
    grid = np.stack(np.meshgrid(a, a, indexing="ij"), -1).reshape(-1, 2)
    elsewhere = np.inf
    for level in range(3):
        translations = (grid @ axes).astype(np.float32)
        cost, seen = views.mean_cost(points[None] + translations[:, None], colours[None])
        i = int(np.argmin(cost))
        if level == 0:
            far = np.linalg.norm(grid - grid[i], axis=-1) >= config.unique_m
            elsewhere = float(cost[far].min()) if far.any() else np.inf
        fine = np.arange(-4, 5) * config.step / 4 ** (level + 1)
        grid = grid[i] + np.stack(np.meshgrid(fine, fine, indexing="ij"), -1).reshape(-1, 2)
    return translations[i], float(cost[i]), float(seen[i]), elsewhere


def _landing(views: _Views, points: np.ndarray, colours: np.ndarray, excluded: np.ndarray) -> np.ndarray:
    """``[V, H, W]``: the other keyframe's pixels where ``points`` land at that camera's depth and
    colour (closed over 3 x 3: the points are as dense as their own image's pixels)."""
    out = np.zeros((len(views.images), views.height, views.width), np.uint8)
    best, which = views.costs(points, colours)
    good = np.isfinite(best) & (best < views.config.threshold)
    for c in np.unique(which[good]):
        row, col = views.pixel(views.project(points[good & (which == c)], c)[0])
        out[c, row, col] = 1
        out[c] = cv2.morphologyEx(out[c], cv2.MORPH_CLOSE, np.ones((3, 3), np.uint8))
    return (out > 0) & ~excluded


def rig_objects(
    images: np.ndarray,  # [2, V, H, W, 3] uint8
    depth: np.ndarray,  # [2, V, H, W] z-depth
    rigid: np.ndarray,  # [2, V, H, W, 2] pixels
    excluded: np.ndarray,  # [2, V, H, W] bool: sky, outside valid_mask, moving already: never searched
    intrinsics: np.ndarray,  # [V, 3, 3]
    cam_to_local: np.ndarray,  # [2, V, 4, 4]
    up: np.ndarray,  # [3] the ground plane's normal, local frame
    config: RigObjectConfig = RigObjectConfig(),
) -> list[RigObject]:
    """The objects found across the rig (module docstring), both keyframes searched; a pixel
    belongs to at most one object (the first keyframe's first)."""
    num_views, height, width = depth.shape[1:]
    grid = pixel_grid(height, width)
    rgb = images.astype(np.float32) / 255
    smooth = np.stack([[cv2.blur(rgb[k, v], (3, 3)) for v in range(num_views)] for k in (0, 1)])
    taken = excluded.copy()
    found = []
    rng = np.random.default_rng(0)
    for k in (0, 1):
        o = 1 - k
        views = _Views(smooth[o], depth[o], intrinsics, cam_to_local[o], config)
        axes = _plane_axes(cam_to_local[k], up)
        for v in range(num_views):
            cost, outside = warp_cost(rgb[k, v], rgb[o, v], rigid[k, v], config.box, grid)
            candidates = (((cost > config.threshold) | outside) & ~taken[k, v] & (depth[k, v] > 0)).astype(np.uint8)
            candidates = cv2.morphologyEx(candidates, cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))
            count, labels, stats, _ = cv2.connectedComponentsWithStats(candidates, connectivity=8)
            for label in np.argsort(-stats[1:, cv2.CC_STAT_AREA]) + 1:
                if stats[label, cv2.CC_STAT_AREA] < config.min_pixels:
                    break
                blob = (labels == label) & ~taken[k, v]
                ys, xs = np.nonzero(blob)
                if len(xs) < config.min_pixels or np.count_nonzero(outside[ys, xs]) < config.leaving * len(xs):
                    continue
                pick = rng.choice(len(xs), min(config.samples, len(xs)), replace=False)
                every = _lift(depth[k, v], intrinsics[v], cam_to_local[k, v], ys, xs)  # the blob's points
                colour = smooth[k, v][ys, xs]
                points, colours = every[pick].astype(np.float32), colour[pick]
                still, _ = views.mean_cost(points, colours)
                if still <= config.still_cost:
                    continue
                translation, best, seen, elsewhere = _search(views, points, colours, axes, config)
                if config.depth_scales:  # the same rays at other depths, standing still
                    centre = cam_to_local[k, v, :3, 3].astype(np.float32)
                    scales = np.asarray(config.depth_scales, np.float32)[:, None, None]
                    parallax, _ = views.mean_cost(centre + scales * (points - centre), colours[None])
                    elsewhere = min(elsewhere, float(parallax.min()))
                if not (
                    best <= config.ratio * float(still)
                    and seen >= config.min_seen
                    and np.linalg.norm(translation) >= config.min_motion
                    and best <= config.unique * elsewhere
                ):
                    continue
                moved, _ = views.costs(every + translation, colour)
                standing, _ = views.costs(every, colour)
                better = (moved < config.threshold) & ~(standing <= moved)
                mask = np.zeros((height, width), np.uint8)
                mask[ys[better], xs[better]] = 1
                mask = cv2.morphologyEx(mask, cv2.MORPH_OPEN, np.ones((3, 3), np.uint8)) > 0
                if np.count_nonzero(mask) < config.min_pixels // 2:
                    continue
                kept = mask[ys, xs]  # the object's pixels among the blob's (mask is within the blob)
                landing = _landing(views, every[kept] + translation, colour[kept], taken[o])
                taken[k, v] |= mask
                taken[o] |= landing
                found.append(RigObject(k, v, mask, translation, landing, best, float(still)))
    return found


def with_rig_objects(scene_flow, applied, depth, rigid, sky, batch, pair, config: RigObjectConfig):
    """``scene_flow`` and ``applied`` with the objects `rig_objects` finds across the rig moving by
    their translation (and their landing pixels at the other keyframe back by it)."""
    up = batch.local_to_world[:3, :3].T.cpu().numpy() @ pair.ego_to_world[0][:3, 2]  # the ego's up, local frame
    found = rig_objects(
        pair.images, depth.detach().cpu().numpy(), rigid.detach().cpu().numpy(), (sky | applied).cpu().numpy(),
        batch.intrinsics.cpu().numpy(), batch.cam_to_local.cpu().numpy(), up, config,
    )  # fmt: skip
    if not found:
        return scene_flow, applied
    flows, moving = scene_flow.clone(), applied.clone()
    for obj in found:
        t = torch.as_tensor(obj.translation, dtype=flows.dtype, device=flows.device)
        here = torch.from_numpy(obj.pixels).to(flows.device)
        there = torch.from_numpy(obj.landing).to(flows.device)
        flows[obj.keyframe, obj.camera][here] = t
        moving[obj.keyframe, obj.camera] |= here
        flows[1 - obj.keyframe][there] = -t
        moving[1 - obj.keyframe] |= there
    return flows, moving
