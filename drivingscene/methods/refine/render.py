"""Rendering the input views during refinement, and the loss against them.

Each input image (keyframe k, camera v) is rendered at its own capture pose and time from *all*
Gaussians: its own keyframe's where they are, the other keyframe's moved there by their flow. That
is what ties depth and flow across time and cameras: a Gaussian at the wrong depth, or with the
wrong flow, lands on the wrong pixel of the other keyframe's images. They are combined with the
blend the reconstruction is shown with (``RefineConfig.blend``, by default `DEFAULT_BLEND`: one
layer per input image, weighed by time and by the angle between the cameras' axes), so that the
steps fit the pictures the user sees, not another rendering of the same Gaussians.

Loss per rendered image, the paper's rendering loss (`models.losses.render_loss`) with
``RefineConfig.lpips_weight`` (by default 0: L2 alone) over the pixels that see the world
(``valid_mask``), and with LiDAR
``lidar_weight`` times the mean |rendered depth - LiDAR depth| / LiDAR depth where there is a
return (a relative L1: near and far returns count alike).

The sky is not made of Gaussians: each view's sky colour (the reconstruction's sky SH, along the
world viewing directions) is computed once and composited behind the splats, as ``render_gaussians``
does.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from drivingscene.gaussians.core import Gaussians
from drivingscene.geometry.se3 import invert_rigid
from drivingscene.methods.refine.inputs import RefineInputs, scaled_inputs
from drivingscene.models.losses import render_loss
from drivingscene.render.scene import render_gaussians
from drivingscene.render.sky import ray_directions, sky_colors

MIN_PERCEPTUAL_SIZE = 32


@dataclass(frozen=True)
class ViewSet:
    """The 2V input views at one image scale, keyframe-major (image b = k * V + v)."""

    images: Tensor  # [2V, 3, h, w]
    intrinsics: Tensor  # [2V, 3, 3]
    world_to_cam: Tensor  # [2V, 4, 4] local frame
    times: Tensor  # [2V] normalised capture times
    sky: Tensor  # [2V, 3, h, w] background colour
    valid: Tensor | None  # [2V, h, w] bool
    lidar: Tensor | None  # [2V, h, w] LiDAR depth, 0 where none
    blend: str  # how both keyframes' Gaussians combine (`render_gaussians`)
    axes: Tensor | None  # [2, V, 3] input cameras' optical axes, local frame (blend "cameras")

    @property
    def size(self) -> tuple[int, int]:
        return int(self.images.shape[-2]), int(self.images.shape[-1])


def view_set(inputs: RefineInputs, sky_sh: Tensor | None, scale: float, blend: str, axes: Tensor | None) -> ViewSet:
    """The input views at ``scale`` of their size (area-resized; a pixel is valid where every pixel
    it covers is; a LiDAR return is kept at the nearest return within the pixel), rendered with
    ``blend`` (``axes``: the input cameras' optical axes in the local frame, for "cameras")."""
    small = scaled_inputs(inputs, scale)
    size = small.image_size
    images = small.images.flatten(0, 1)
    k = small.intrinsics.repeat(2, 1, 1)
    c2l = inputs.cam_to_local.flatten(0, 1)
    valid = None if small.valid is None else small.valid.repeat(2, 1, 1)
    lidar = None if small.lidar is None else small.lidar.flatten(0, 1)
    if sky_sh is None:
        sky = torch.zeros_like(images)
    else:
        c2w = (inputs.local_to_world[None] @ c2l.double()).float()
        sky = sky_colors(sky_sh.float(), ray_directions(c2w, k, *size)).permute(0, 3, 1, 2)
    return ViewSet(images, k, invert_rigid(c2l.double()).float(), inputs.times.flatten(), sky, valid, lidar, blend, axes)


def render_views(gaussians: Gaussians, views: ViewSet, index: list[int], max_layers: int) -> tuple[Tensor, Tensor, Tensor]:
    """Colours ``[B, 3, h, w]`` (over the sky), depths and alphas ``[B, h, w]`` of views ``index``;
    views captured at one time render in one batch."""
    height, width = views.size
    times = views.times[index]
    colors, depths, alphas = [None] * len(index), [None] * len(index), [None] * len(index)
    for t in times.unique().tolist():
        group = [i for i, ti in enumerate(times.tolist()) if ti == t]
        idx = [index[i] for i in group]
        out = render_gaussians(
            gaussians,
            t,
            views.world_to_cam[idx],
            views.intrinsics[idx],
            height,
            width,
            blend=views.blend,
            source_axes=views.axes,
            max_layers=max_layers,
        )
        rgb = out.colors.permute(0, 3, 1, 2) + (1 - out.alphas[:, None]) * views.sky[idx]
        for j, i in enumerate(group):
            colors[i], depths[i], alphas[i] = rgb[j], out.depths[j], out.alphas[j]
    return torch.stack(colors), torch.stack(depths), torch.stack(alphas)


def views_loss(
    gaussians: Gaussians,
    views: ViewSet,
    index: list[int],
    perceptual,
    *,
    lpips_weight: float,
    lidar_weight: float,
    max_layers: int,
) -> tuple[Tensor, dict[str, float]]:
    """The loss of the module docstring over views ``index``, and its terms (floats, for logs)."""
    colors, depths, _ = render_views(gaussians, views, index, max_layers)
    pred = colors.clamp(0, 1)
    target = views.images[index]
    mask = None if views.valid is None else views.valid[index]
    if min(views.size) < MIN_PERCEPTUAL_SIZE:  # the perceptual network needs 32 pixels or more
        perceptual = None
    loss = render_loss(pred, target, perceptual, lpips_weight, mask)
    terms = {"render": float(loss.detach())}
    if views.lidar is not None and lidar_weight > 0:
        lidar = views.lidar[index]
        has = lidar > 0
        if mask is not None:
            has = has & mask
        if bool(has.any()):
            rel = ((depths - lidar).abs() / lidar.clamp(min=1e-3))[has].mean()
            loss = loss + lidar_weight * rel
            terms["lidar"] = float(rel.detach())
    return loss, terms
