"""The parameters refinement optimises, and the Gaussians they make.

Every Gaussian of a reconstruction came from one pixel of one input image (``keyframes``,
``cameras``); its pixel and its ray are recovered by projecting its mean into that image's camera.
Along the ray it moves by a log-depth offset ``d``:

    mean(d)       = origin + exp(d) (mean_0 - origin)      (origin: the camera centre)
    log_scales(d) = log_scales + d                          (the same footprint in its own view)

so it only ever slides along its own ray and keeps covering its pixel. The other groups are the
raw values: SH colour, opacity logits, log scales, and the flow of the dynamic Gaussians (static
ones stay static). Gaussians whose camera is unknown (-1, e.g. after merging) keep their depth.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch
from torch import Tensor

from drivingscene.gaussians.core import Gaussians
from drivingscene.geometry.camera import project
from drivingscene.geometry.se3 import invert_rigid, transform_points

GROUPS = ("depth", "color", "opacity", "scale", "flow")


@dataclass(frozen=True)
class GaussianRays:
    """Each Gaussian's source pixel and camera centre (local frame)."""

    origins: Tensor  # [N, 3] camera centre of its source image
    pixels: Tensor  # [N] int64 flat index into [2, V, H, W]; -1: no source pixel (no depth parameter)
    depths: Tensor  # [N] camera z of the mean in its source image, metres (0 without a pixel)

    @property
    def has_ray(self) -> Tensor:
        return self.pixels >= 0


def gaussian_rays(
    gaussians: Gaussians,  # local frame
    cam_to_local: Tensor,  # [2, V, 4, 4]
    intrinsics: Tensor,  # [V, 3, 3]
    image_size: tuple[int, int],
) -> GaussianRays:
    """Pixels and ray origins of Gaussians made per pixel (see module docstring)."""
    height, width = image_size
    num_views = cam_to_local.shape[1]
    cams = gaussians.cameras.clamp(min=0)
    known = (gaussians.cameras >= 0) & (gaussians.cameras < num_views)
    image = gaussians.keyframes * num_views + cams  # [N]
    c2l = cam_to_local.flatten(0, 1)  # [2V, 4, 4]
    origins = c2l[image, :3, 3]
    local = transform_points(invert_rigid(c2l)[image], gaussians.means[:, None])[:, 0]  # [N, 3] camera frame
    uv, z = project(local[:, None], intrinsics[cams])
    uv = uv[:, 0].round().long()
    inside = (z[:, 0] > 1e-3) & (uv[:, 0] >= 0) & (uv[:, 0] < width) & (uv[:, 1] >= 0) & (uv[:, 1] < height)
    ok = known & inside
    pixels = (image * height + uv[:, 1]) * width + uv[:, 0]
    return GaussianRays(
        origins=torch.where(ok[:, None], origins, gaussians.means),
        pixels=torch.where(ok, pixels, -1),
        depths=torch.where(ok, z[:, 0], torch.zeros_like(z[:, 0])),
    )


class RefineParams:
    """Leaf tensors for the groups being optimised; ``gaussians()`` builds the differentiable set."""

    def __init__(self, base: Gaussians, rays: GaussianRays, groups: tuple[str, ...]):
        self.base = base
        self.rays = rays
        self.groups = groups
        self.dynamic = base.dynamic.nonzero().squeeze(1)  # [D]
        self.values: dict[str, Tensor] = {
            "depth": torch.zeros(len(base)),
            "color": base.sh.clone(),
            "opacity": base.opacity_logits.clone(),
            "scale": base.log_scales.clone(),
            "flow": base.flows[self.dynamic].clone(),
        }
        for name in groups:
            self.values[name].requires_grad_(True)

    def parameters(self, name: str) -> Tensor:
        return self.values[name]

    def gaussians(self) -> Gaussians:
        """The Gaussians (local frame) at the current values, differentiable in the optimised groups."""
        v, base, rays = self.values, self.base, self.rays
        offset = torch.where(rays.has_ray, v["depth"], torch.zeros_like(v["depth"]))
        means = rays.origins + torch.exp(offset)[:, None] * (base.means - rays.origins)
        flows = base.flows
        if self.dynamic.numel():
            flows = flows.index_put((self.dynamic,), v["flow"])
        return replace(
            base,
            means=means,
            log_scales=v["scale"] + offset[:, None],
            opacity_logits=v["opacity"],
            sh=v["color"],
            flows=flows,
        )

    def state(self) -> dict[str, Tensor]:
        """A detached copy of every value (to go back to after a bad step)."""
        return {k: t.detach().clone() for k, t in self.values.items()}

    def load(self, state: dict[str, Tensor]) -> None:
        with torch.no_grad():
            for k, t in state.items():
                self.values[k].copy_(t)

    def finite(self) -> bool:
        return all(bool(torch.isfinite(t).all()) for k, t in self.values.items() if k != "opacity") and not bool(
            torch.isnan(self.values["opacity"]).any()
        )

    def set_depth(self, log_offset: Tensor) -> None:
        """Start the depth offsets at ``log_offset`` ``[N]`` (0 where a Gaussian has no ray)."""
        with torch.no_grad():
            self.values["depth"].copy_(torch.where(self.rays.has_ray, log_offset, torch.zeros_like(log_offset)))
