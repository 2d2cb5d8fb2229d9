"""Visibility checks between the views of a pair: keep out Gaussians that another camera sees through.

Each pixel of each input image becomes a Gaussian at its predicted depth. Where that depth is
wrong, or the pixel straddles a depth edge or an image border, the Gaussian floats in front of what
a neighbouring camera (or the same camera at the other keyframe) actually saw, and it is painted
over that camera's view: doubled kerbs, ghost pillars. Free-space carving removes such Gaussians:
for a Gaussian of image i and another image j (taken at time k_j),

    x = the Gaussian's centre at time k_j (moved by its flow if it is dynamic)
    (u, v, z) = x projected into j
    violation if z < (1 - margin) * min(depth_j over a window around (u, v))

i.e. camera j saw a surface clearly behind the Gaussian along that ray, so there is nothing where
the Gaussian is. The window minimum makes the test conservative at depth edges and for thin
structures (a pole one pixel off is compared with the pole, not the wall behind it). Pixels
without depth in j (off the valid mask) give no vote; j's sky counts as infinitely far. A
Gaussian is dropped when at least ``min_votes`` images see through it. With exact depth nothing is
dropped (tests: the oracle reconstruction loses no Gaussian).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from drivingscene import kernels
from drivingscene.gaussians.core import Gaussians

SKY_DEPTH = 1e6  # metres: the sky in a depth map used for carving
NO_DEPTH = 1e12  # a pixel that gives no vote (off the valid mask)


@dataclass(frozen=True)
class CarveConfig:
    margin: float = 0.1  # relative depth margin of a violation
    window: int = 3  # odd window (pixels) of the depth minimum
    min_votes: int = 1  # images that must see through a Gaussian to drop it
    # "all": every other image of the pair votes; "same_time": only the other cameras of the
    # Gaussian's own keyframe (no motion between them to get wrong).
    voters: str = "all"

    def __post_init__(self):
        if self.window < 1 or self.window % 2 == 0:
            raise ValueError(f"CarveConfig.window: expected an odd number >= 1, found {self.window}")
        if self.voters not in ("all", "same_time"):
            raise ValueError(f"CarveConfig.voters: expected all or same_time, found {self.voters!r}")


def carving_depths(depth: Tensor, sky: Tensor, world: Tensor | None, window: int) -> Tensor:
    """``[B, H, W]``: per pixel the minimum over ``window`` of the depth maps ``[B, H, W]``, where
    sky pixels (``sky`` [B, H, W] bool) are infinitely far and pixels off ``world`` give no vote."""
    d = torch.where(sky, torch.full_like(depth, SKY_DEPTH), depth)
    if world is not None:
        d = torch.where(world, d, torch.full_like(d, NO_DEPTH))
    if window > 1:
        d = -F.max_pool2d(-d[:, None], window, stride=1, padding=window // 2)[:, 0]
    return d


def see_through_votes(
    gaussians: Gaussians,
    image_ids: Tensor,  # [N] long: the image (keyframe * V + camera) each Gaussian came from
    world_to_cam: Tensor,  # [B, 4, 4] every image of the pair (B = 2V, keyframe-major)
    intrinsics: Tensor,  # [B, 3, 3]
    depths: Tensor,  # [B, H, W] from `carving_depths`
    times: Tensor,  # [B] normalised time of each image (0 or 1)
    config: CarveConfig,
    backend: str = "auto",
) -> Tensor:
    """``[N]`` int: how many images see through each Gaussian (module docstring). ``backend``:
    the compiled kernel (`drivingscene.kernels.see_through_votes`, one pass per Gaussian) or the
    torch path."""
    g = gaussians
    if kernels.available(kernels.see_through_votes, backend, g.means, depths, world_to_cam):
        return kernels.see_through_votes(
            g.means,
            g.flows,
            g.keyframes,
            image_ids,
            world_to_cam,
            intrinsics,
            depths,
            times.float(),
            config.margin,
            config.voters == "same_time",
            NO_DEPTH,
        )
    return _votes_torch(g, image_ids, world_to_cam, intrinsics, depths, times, config)


def _votes_torch(gaussians, image_ids, world_to_cam, intrinsics, depths, times, config) -> Tensor:
    batch, height, width = depths.shape
    votes = torch.zeros(len(gaussians), dtype=torch.int32, device=depths.device)
    num_views = batch // 2
    for j in range(batch):
        voters = image_ids != j
        if config.voters == "same_time":
            voters &= (image_ids // num_views) == (j // num_views)
        index = voters.nonzero().squeeze(1)
        if index.numel() == 0:
            continue
        g = gaussians.index(index)
        points = g.means_at(times[j]) @ world_to_cam[j, :3, :3].T + world_to_cam[j, :3, 3]
        z = points[:, 2]
        inv_z = 1.0 / z.clamp(min=1e-6)
        u = intrinsics[j, 0, 0] * points[:, 0] * inv_z + intrinsics[j, 0, 1] * points[:, 1] * inv_z + intrinsics[j, 0, 2]
        v = intrinsics[j, 1, 1] * points[:, 1] * inv_z + intrinsics[j, 1, 2]
        col, row = u.round().long(), v.round().long()
        inside = (z > 0.1) & (col >= 0) & (col < width) & (row >= 0) & (row < height)
        seen = torch.full_like(z, NO_DEPTH)
        seen[inside] = depths[j, row[inside], col[inside]]
        through = inside & (seen < NO_DEPTH) & (z < (1.0 - config.margin) * seen)
        votes.index_add_(0, index, through.to(torch.int32))
    return votes


def carve(
    gaussians: Gaussians,
    image_ids: Tensor,  # [N]
    world_to_cam: Tensor,  # [B, 4, 4]
    intrinsics: Tensor,  # [B, 3, 3]
    depth: Tensor,  # [B, H, W] predicted depth of every image
    sky: Tensor,  # [B, H, W] bool
    world: Tensor | None,  # [B, H, W] bool: pixels that see the world
    config: CarveConfig = CarveConfig(),
) -> Tensor:
    """``[N]`` bool: the Gaussians to keep (no image sees through them)."""
    depths = carving_depths(depth, sky, world, config.window)
    times = torch.arange(depth.shape[0], device=depth.device) // (depth.shape[0] // 2)
    votes = see_through_votes(gaussians, image_ids, world_to_cam, intrinsics, depths, times.float(), config)
    return votes < config.min_votes
