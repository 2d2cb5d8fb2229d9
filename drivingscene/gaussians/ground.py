"""The ground as a background: the road plane and its colour (drawn by `drivingscene.render.sky.with_ground`).

The road is the ego frame's z = 0 plane (as `drivingscene.data.road_plane` takes it); its colour is
the median colour of the Gaussians that lie on it.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

# Gaussians within this distance (metres) of the road plane colour the ground.
GROUND_BAND = 0.25
# Fewer Gaussians on the plane than this: no ground (the sky model alone).
GROUND_MIN_GAUSSIANS = 100


@dataclass(frozen=True)
class Ground:
    """The road plane as background: ``plane`` ``[4]`` (unit normal n pointing up, offset d: the
    plane is ``n . x + d = 0`` in the world frame) and its colour ``rgb`` ``[3]`` in [0, 1]."""

    plane: Tensor
    rgb: Tensor


def road_plane(ego_to_world: Tensor) -> Tensor:
    """``[4]`` the ego frame's z = 0 plane (the road the rig is mounted over, as
    `drivingscene.data.road_plane` takes it) of an ego pose ``[4, 4]``, in the world frame."""
    n = ego_to_world[:3, 2].double()
    n = n / n.norm()
    return torch.cat([n, -(n @ ego_to_world[:3, 3].double())[None]]).float()


def fit_ground(means: Tensor, rgb: Tensor, plane: Tensor) -> Ground | None:
    """The ground of Gaussians at ``means`` ``[N, 3]`` with colours ``rgb`` ``[N, 3]``: the median
    colour of those within `GROUND_BAND` of ``plane`` ``[4]``; None if fewer than
    `GROUND_MIN_GAUSSIANS` lie there."""
    height = means.float() @ plane[:3].to(means.device) + plane[3].to(means.device)
    on = height.abs() < GROUND_BAND
    if int(on.sum()) < GROUND_MIN_GAUSSIANS:
        return None
    colour = rgb[on].float().clamp(0.0, 1.0).median(0).values
    return Ground(plane.float().cpu(), colour.cpu())
