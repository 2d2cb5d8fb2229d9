"""A plane sweep over depth along each pixel's ray: the global search that starts refinement.

Gradients of a photometric loss move a surface by about a pixel of misregistration; the model's
depth on real frames is off by factors of 2-5 (docs/real-data.md), tens of pixels of parallax.
So before any gradient step every pixel of every input image tries a grid of depths, uniform in
inverse depth between ``near`` and ``far``, and keeps the one at which the other images of the
pair agree with it best: the photometric error of L_loc (0.85 (1 - SSIM) / 2 + 0.15 L1,
as `models.losses.photometric_error`, on luma, with the targets' window statistics computed once) averaged over a small window, the minimum over the
sources that see the point (the same camera at the other keyframe, and both keyframes of the
neighbouring cameras), as monodepth2 takes it over its sources.

Such winner-take-all depths are noisy (flat cost on sky and road, repeated texture, moving
objects), so only those that another image confirms are kept: the point, moved into a source,
lands within ``consistency`` of that source's own choice. Their ratios to the model's depth
become a smooth correction of the model's depth (normalised convolution of the log ratio at
growing widths): the model keeps its shapes, the sweep sets their scale region by region.

The correction is noisy too, and where the model's depth is right (most procedural pairs) it would
only add the sweep's noise. An image whose confirmed pixels disagree with the model by more than
``trigger`` (median ratio) is corrected wholly: its scale is wrong. In the others the cost volume
arbitrates (``arbitration``): at every search pixel the photometric cost at the corrected depth is
compared with the cost at the model's depth, and the correction is kept by the local share
(Gaussian window of ``arbitration`` search pixels) of pixels where it lowers the cost less the
share where it raises it. (Before, those images kept the model's depth; on the real DDAD pairs
no image passed the trigger although whole cameras were 30-50 % off, docs/refinement.md.)

With LiDAR (refinement's ``--lidar``) every return is a confirmed sample (weight ``lidar_weight``)
of the correction, whatever the trigger, and its pixel takes the LiDAR depth; the correction
is then not arbitrated (LiDAR is stronger evidence than the photometric cost).

Everything runs in the pair's local frame, without gradients.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from drivingscene.geometry.camera import pixel_grid, project, scale_intrinsics, unproject
from drivingscene.geometry.se3 import invert_rigid, transform_points

INVALID = 1e3  # cost of a sample that falls outside the source, behind it, or on its masked pixels


@dataclass(frozen=True)
class SweepConfig:
    near: float = 1.5  # metres, the nearest depth tried
    far: float = 150.0  # metres, the farthest
    # Depths tried (uniform in inverse depth) and the image scale of the search: 48 at 0.375 cost
    # 1.5-1.8 CPU-seconds for a 6x176x320 pair (one thread), within 0.02 AbsRel of 64 at 0.5
    # (3.5-4.3 s) on validation pairs with the depth made 3x too near (docs/refinement.md).
    hypotheses: int = 48
    scale: float = 0.375
    window: int = 5  # odd box window (search pixels) over which the error is averaged
    # A choice is a candidate when its cost is below this fraction of the pixel's median cost
    # over the depths that some source sees (a clear minimum), below ``max_cost``, and some source
    # sees the point at ``min_seen`` of the depths at least (a near point that leaves every
    # source is seen only at wrong, far depths).
    max_ratio: float = 0.8
    max_cost: float = 0.3
    min_seen: float = 0.5
    consistency: float = 0.05  # relative depth agreement with a source's own choice
    trigger: float = 1.5  # median ratio to the model's depth beyond which an image is corrected wholly
    # Gaussian sigma (search pixels) of the photometric arbitration of the correction in the other
    # images (module docstring); None: they keep the model's depth
    arbitration: float | None = 6.0
    widths: tuple[float, ...] = (3.0, 10.0, 30.0)  # Gaussian sigmas (search pixels) of the correction
    lidar_weight: float = 4.0  # weight of a LiDAR return against a confirmed photometric sample
    # sources: the same camera at the other keyframe and the neighbours at the same keyframe
    # ("near"), or also the neighbours at the other keyframe ("all")
    sources: str = "all"

    def __post_init__(self):
        if not 0 < self.near < self.far:
            raise ValueError(f"SweepConfig: expected 0 < near < far, found {self.near}, {self.far}")
        if self.sources not in ("near", "all"):
            raise ValueError(f"SweepConfig.sources: expected 'near' or 'all', found {self.sources!r}")
        if self.hypotheses < 3 or self.window < 1 or self.window % 2 == 0 or not 0 < self.scale <= 1:
            raise ValueError("SweepConfig: expected hypotheses >= 3, an odd window >= 1 and 0 < scale <= 1")


@dataclass(frozen=True)
class SweepResult:
    depth: Tensor  # [2, V, H, W] corrected z-depth (0 where the prior is 0: sky, masked)
    confirmed: Tensor  # [2, V, H, W] bool: pixels whose sweep depth another image confirmed
    corrected: Tensor  # [2, V] bool: images whose depth was corrected


def neighbour_cameras(cam_to_ego: Tensor) -> list[tuple[int, int]]:
    """Each camera's left and right neighbour by viewing yaw (none for a single camera)."""
    axis = cam_to_ego[:, :3, 2]
    order = torch.atan2(axis[:, 1], axis[:, 0]).argsort().tolist()
    n = len(order)
    if n < 2:
        return []
    out = [(-1, -1)] * n
    for i, v in enumerate(order):
        out[v] = (order[(i - 1) % n], order[(i + 1) % n])
    return out


def source_indices(num_views: int, neighbours: list[tuple[int, int]], kind: str = "all") -> Tensor:
    """``[S, 2V]`` flat source image (k * V + v) for each target image (keyframe-major): the same
    camera at the other keyframe, then each neighbour at the same keyframe (and, with ``"all"``,
    at the other keyframe)."""
    kf = torch.arange(2).repeat_interleave(num_views)
    cam = torch.arange(num_views).repeat(2)
    sets = [(1 - kf) * num_views + cam]
    for side in range(2 if neighbours else 0):
        other = torch.tensor([neighbours[v][side] for v in cam.tolist()])
        sets.append(kf * num_views + other)
        if kind == "all":
            sets.append((1 - kf) * num_views + other)
    return torch.stack(sets)


def inverse_depths(config: SweepConfig) -> Tensor:
    """``[J]`` the inverse depths tried, nearest first."""
    return torch.linspace(1.0 / config.near, 1.0 / config.far, config.hypotheses)


def _box(x: Tensor, window: int) -> Tensor:
    """Mean over ``window`` x ``window`` boxes of ``[B, H, W]`` (replicate padding)."""
    if window == 1:
        return x
    pad = window // 2
    return F.avg_pool2d(F.pad(x[:, None], (pad,) * 4, mode="replicate"), window, stride=1)[:, 0]


def _sample(image: Tensor, uv: Tensor, mode: str = "bilinear") -> Tensor:
    """``image`` ``[B, C, h, w]`` at pixel coordinates ``uv`` ``[B, h, w, 2]`` (border-clamped)."""
    height, width = image.shape[-2:]
    grid = torch.stack([uv[..., 0] / (width - 1), uv[..., 1] / (height - 1)], -1) * 2 - 1
    return F.grid_sample(image, grid, mode=mode, padding_mode="border", align_corners=True)


def _inside(uv: Tensor, z: Tensor, height: int, width: int) -> Tensor:
    return (z > 0.1) & (uv[..., 0] >= 0) & (uv[..., 0] <= width - 1) & (uv[..., 1] >= 0) & (uv[..., 1] <= height - 1)


def _box3(x: Tensor) -> Tensor:
    """3x3 box mean of ``[B, 1, h, w]`` with reflection padding (monodepth2's SSIM window)."""
    x = F.pad(x, (1, 1, 1, 1), mode="reflect")
    rows = x[..., :-2, :] + x[..., 1:-1, :] + x[..., 2:, :]
    return (rows[..., :-2] + rows[..., 1:-1] + rows[..., 2:]) / 9.0


class PhotometricError:
    """L_loc's per-pixel error 0.85 (1 - SSIM) / 2 + 0.15 |x - y| (3x3 box SSIM) against fixed
    targets ``[B, 1, h, w]``: their means and variances are computed once for every hypothesis."""

    def __init__(self, targets: Tensor):
        self.y = targets
        self.mu_y = _box3(targets)
        self.var_y = _box3(targets * targets) - self.mu_y**2

    def __call__(self, x: Tensor) -> Tensor:  # [B, 1, h, w] -> [B, h, w]
        c1, c2 = 0.01**2, 0.03**2
        mu_x = _box3(x)
        var_x = _box3(x * x) - mu_x**2
        cov = _box3(x * self.y) - mu_x * self.mu_y
        ssim = ((2 * mu_x * self.mu_y + c1) * (2 * cov + c2)) / ((mu_x**2 + self.mu_y**2 + c1) * (var_x + self.var_y + c2))
        return (0.85 * ((1 - ssim) / 2).clamp(0, 1) + 0.15 * (x - self.y).abs())[:, 0]


def sweep_costs(
    luma: Tensor,  # [B, 1, h, w] the 2V images at the search's scale, keyframe-major
    intrinsics: Tensor,  # [B, 3, 3] at the search's scale
    cam_to_local: Tensor,  # [B, 4, 4]
    sources: Tensor,  # [S, B] flat source index per target
    valid: Tensor | None,  # [B, h, w] bool: pixels that see the world
    config: SweepConfig,
    should_stop=None,
) -> Tensor | None:
    """Cost volume ``[J, B, h, w]`` (see module docstring); None when ``should_stop()`` said so."""
    num, _, height, width = luma.shape
    pixels = torch.cat([pixel_grid(height, width), torch.ones(height, width, 1)], -1).reshape(-1, 3)
    rays = pixels @ torch.linalg.inv(intrinsics).transpose(-1, -2)  # [B, hw, 3], z = 1
    to_source = [invert_rigid(cam_to_local[s]) @ cam_to_local for s in sources]
    off = None if valid is None else (~valid)[:, None].float()
    error_of = PhotometricError(luma)
    costs = []
    for q in inverse_depths(config).tolist():
        if should_stop is not None and should_stop():
            return None
        best = torch.full((num, height, width), INVALID)
        for s, transform in zip(sources, to_source):
            uv, z = project(transform_points(transform, rays / q), intrinsics[s])
            uv, z = uv.view(num, height, width, 2), z.view(num, height, width)
            ok = _inside(uv, z, height, width)
            if off is not None:
                ok &= _sample(off[s], uv)[:, 0] == 0  # the sample reads no masked pixel
            error = torch.where(ok, error_of(_sample(luma[s], uv)), torch.full_like(best, INVALID))
            best = torch.minimum(best, _box(error, config.window))
        costs.append(best)
    return torch.stack(costs)


def choose_depth(costs: Tensor, config: SweepConfig) -> tuple[Tensor, Tensor]:
    """Per pixel, the depth ``[B, h, w]`` of the least cost (refined by a parabola through its
    neighbours, in inverse depth) and whether it is a candidate ``[B, h, w]`` (module docstring)."""
    q = inverse_depths(config)
    count = costs.shape[0]
    best, index = costs.min(0)
    lo, hi = (index - 1).clamp(min=0), (index + 1).clamp(max=count - 1)
    c0, c1 = costs.gather(0, lo[None])[0], costs.gather(0, hi[None])[0]
    curvature = c0 + c1 - 2 * best
    inner = (index > 0) & (index < count - 1) & (curvature > 1e-6)
    shift = torch.where(inner, 0.5 * (c0 - c1) / curvature.clamp(min=1e-6), torch.zeros_like(best)).clamp(-0.5, 0.5)
    inverse = q[index] + shift * (q[1] - q[0])
    seen = costs < INVALID / 2
    median = torch.where(seen, costs, torch.full_like(costs, float("nan"))).nanmedian(0).values
    candidate = (best < config.max_cost) & (best < config.max_ratio * median) & inner
    candidate &= seen.float().mean(0) >= config.min_seen
    return 1.0 / inverse.clamp(min=1.0 / (config.far * 4)), candidate


def confirmed_by_sources(
    depth: Tensor,  # [B, h, w]
    intrinsics: Tensor,  # [B, 3, 3]
    cam_to_local: Tensor,  # [B, 4, 4]
    sources: Tensor,  # [S, B]
    tolerance: float,
) -> Tensor:
    """``[B, h, w]`` bool: pixels whose point, moved into some source, lands inside it at a depth
    within ``tolerance`` (relative) of that source's own depth there."""
    num, height, width = depth.shape
    points = unproject(depth, intrinsics).flatten(1, 2)
    out = torch.zeros_like(depth, dtype=torch.bool)
    for s in sources:
        uv, z = project(transform_points(invert_rigid(cam_to_local[s]) @ cam_to_local, points), intrinsics[s])
        uv, z = uv.view(num, height, width, 2), z.view(num, height, width)
        there = _sample(depth[s][:, None], uv, mode="nearest")[:, 0]
        out |= _inside(uv, z, height, width) & ((z - there).abs() < tolerance * z)
    return out


def _blur(x: Tensor, sigma: float) -> Tensor:
    """Separable Gaussian blur of ``[B, h, w]`` (zero padding: weights and values blur alike)."""
    radius = max(1, int(3 * sigma))
    t = torch.arange(-radius, radius + 1, dtype=x.dtype)
    kernel = torch.exp(-(t**2) / (2 * sigma**2))
    kernel = kernel / kernel.sum()
    x = F.conv2d(F.pad(x[:, None], (radius, radius, 0, 0)), kernel.view(1, 1, 1, -1))
    return F.conv2d(F.pad(x, (0, 0, radius, radius)), kernel.view(1, 1, -1, 1))[:, 0]


def correction_field(log_ratio: Tensor, weight: Tensor, widths: tuple[float, ...]) -> Tensor:
    """A smooth ``[B, h, w]`` field through sparse samples (``weight`` > 0): normalised convolution
    at the finest width that has enough support there, the image's weighted median elsewhere."""
    out = torch.zeros_like(log_ratio)
    for b in range(len(out)):
        has = weight[b] > 0
        if bool(has.any()):
            out[b] = log_ratio[b][has].median()
    for sigma in sorted(widths, reverse=True):
        num, den = _blur(weight * log_ratio, sigma), _blur(weight, sigma)
        out = torch.where(den > 0.02, num / den.clamp(min=1e-6), out)
    return out


def cost_at(costs: Tensor, depth: Tensor, config: SweepConfig) -> Tensor:
    """``[B, h, w]``: the cost volume ``[J, B, h, w]`` read at ``depth`` (linear between the two
    nearest hypotheses in inverse depth, clamped to the swept range)."""
    count = costs.shape[0]
    span = 1.0 / config.near - 1.0 / config.far
    index = ((1.0 / config.near - 1.0 / depth.clamp(min=1e-3)) / span * (count - 1)).clamp(0, count - 1)
    lo = index.floor().long()
    hi = (lo + 1).clamp(max=count - 1)
    frac = index - lo
    return costs.gather(0, lo[None])[0] * (1 - frac) + costs.gather(0, hi[None])[0] * frac


def photometric_preference(costs: Tensor, prior: Tensor, corrected: Tensor, config: SweepConfig) -> Tensor:
    """``[B, h, w]`` in [0, 1]: in a Gaussian window of ``config.arbitration`` search pixels, the
    share of pixels where the corrected depth has the lower photometric cost minus the share where
    it has the higher one, among those where some source sees both depths (0 where the evidence is
    even or against it: flat texture, whose costs tie, keeps the model's depth)."""
    before, after = cost_at(costs, prior, config), cost_at(costs, corrected, config)
    seen = (before < INVALID / 2) & (after < INVALID / 2)
    net = (seen & (after < before)).float() - (seen & (after > before)).float()
    share = _blur(net, config.arbitration) / _blur(seen.float(), config.arbitration).clamp(min=1e-3)
    return share.clamp(0, 1)


def _luma(images: Tensor) -> Tensor:
    """``[B, 3, h, w]`` RGB -> ``[B, 1, h, w]`` luma (Rec. 601)."""
    return (images * images.new_tensor([0.299, 0.587, 0.114]).view(1, 3, 1, 1)).sum(1, keepdim=True)


def _nearest_return(lidar: Tensor, size: tuple[int, int]) -> Tensor:
    """``[B, H, W]`` sparse depth -> ``[B, h, w]``: the nearest return inside each cell, 0 if none."""
    far = torch.where(lidar > 0, lidar, torch.full_like(lidar, 1e9))
    out = -F.adaptive_max_pool2d(-far[:, None], size)[:, 0]
    return torch.where(out < 1e8, out, torch.zeros_like(out))


def corrected_depth(
    images: Tensor,  # [2, V, 3, H, W] in [0, 1]
    intrinsics: Tensor,  # [V, 3, 3]
    cam_to_local: Tensor,  # [2, V, 4, 4] each image's capture pose
    cam_to_ego: Tensor,  # [V, 4, 4] (for the neighbours)
    prior: Tensor,  # [2, V, H, W] the model's depth (0: sky or masked)
    valid: Tensor | None = None,  # [V, H, W] bool: pixels that see the world
    lidar: Tensor | None = None,  # [2, V, H, W] LiDAR depth, 0 where none
    config: SweepConfig = SweepConfig(),
    should_stop=None,
) -> SweepResult | None:
    """The model's depth corrected by the sweep (and LiDAR), as the module docstring says; None if
    ``should_stop()`` said so during the sweep."""
    _, num_views, _, height, width = images.shape
    size = (max(8, round(height * config.scale)), max(8, round(width * config.scale)))
    luma = _luma(F.interpolate(images.flatten(0, 1), size=size, mode="area"))
    k = scale_intrinsics(intrinsics, size[1] / width, size[0] / height).repeat(2, 1, 1)
    c2l = cam_to_local.flatten(0, 1)
    world = (
        None if valid is None else (F.interpolate((~valid)[:, None].float(), size=size, mode="area")[:, 0] == 0).repeat(2, 1, 1)
    )
    sources = source_indices(num_views, neighbour_cameras(cam_to_ego), config.sources)
    costs = sweep_costs(luma, k, c2l, sources, world, config, should_stop)
    if costs is None:
        return None
    depth, candidate = choose_depth(costs, config)
    confirmed = candidate & confirmed_by_sources(depth, k, c2l, sources, config.consistency)
    small_prior = F.interpolate(prior.flatten(0, 1)[:, None], size=size, mode="nearest")[:, 0]
    usable = small_prior > 0 if world is None else (small_prior > 0) & world
    confirmed &= usable
    log_ratio = torch.log(depth.clamp(min=1e-3) / small_prior.clamp(min=1e-3))
    triggered = torch.zeros(2 * num_views, dtype=torch.bool)
    for b in range(2 * num_views):
        if int(confirmed[b].sum()) >= 32:
            triggered[b] = bool(log_ratio[b][confirmed[b]].median().abs() > math.log(config.trigger))
    corrected_images = triggered | ((confirmed.flatten(1).sum(1) >= 32) & (config.arbitration is not None))
    weight = (confirmed & corrected_images[:, None, None]).float()
    if lidar is not None:
        returns = _nearest_return(lidar.flatten(0, 1), size)
        has = (returns > 0) & usable
        weight = torch.where(has, torch.full_like(weight, config.lidar_weight), weight)
        log_ratio = torch.where(has, torch.log(returns.clamp(min=1e-3) / small_prior.clamp(min=1e-3)), log_ratio)
    field = correction_field(log_ratio, weight, config.widths)
    field = torch.where((weight.flatten(1).sum(1) > 0)[:, None, None], field, torch.zeros_like(field))
    if config.arbitration is not None and lidar is None:
        preference = photometric_preference(costs, small_prior, small_prior * torch.exp(field), config)
        field = torch.where(triggered[:, None, None], field, field * preference)
    field = F.interpolate(field[:, None], size=(height, width), mode="bilinear", align_corners=False)[:, 0]
    out = prior.flatten(0, 1) * torch.exp(field)
    if lidar is not None:
        flat = lidar.flatten(0, 1)
        out = torch.where((flat > 0) & (out > 0), flat, out)
    full_confirmed = F.interpolate(confirmed[:, None].float(), size=(height, width), mode="nearest")[:, 0] > 0
    corrected = weight.flatten(1).sum(1) > 0
    return SweepResult(
        depth=out.unflatten(0, (2, num_views)),
        confirmed=full_confirmed.unflatten(0, (2, num_views)),
        corrected=corrected.view(2, num_views),
    )
