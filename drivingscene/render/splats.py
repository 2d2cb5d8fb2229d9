"""Visible (camera, Gaussian) pairs, projected and sorted front to back per camera.

A cheap conservative cull without grad over all ``B x N`` pairs (``project.cull_bound``: depth
range, a bound on the footprint, opacity < 1/255 which can never contribute) keeps ``M``
candidates; only these are projected with grad, so autograd only sees Gaussians that may reach a
pixel. The exact culling rule (``radii == 0``) is applied by the pair finder. Sorting is by camera,
then camera-space ``z`` of the centre (evaluated in float64 whatever the input dtype), ties broken
by Gaussian index (a stable sort): the compositing order.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from drivingscene.render.project import covariances_3d, cull_bound, cull_bound_pairs, project_covariances
from drivingscene.render.sh import sh_to_color

MIN_ALPHA = 1.0 / 255.0


@dataclass(frozen=True)
class Splats:
    """``M`` candidate (camera, Gaussian) pairs in compositing order; camera ``b`` owns rows
    ``camera_offsets[b]:camera_offsets[b+1]``. Rows with ``radii == 0`` are culled and never contribute."""

    means2d: Tensor  # [M, 2] pixels
    conics: Tensor  # [M, 3] px^-2
    depths: Tensor  # [M] camera z, metres
    radii: Tensor  # [M] 3-sigma bounding radius, pixels (no grad)
    opacities: Tensor  # [M]
    colors: Tensor  # [M, C]
    camera_ids: Tensor  # [M] int64
    gaussian_ids: Tensor  # [M] int64
    camera_offsets: Tensor  # [B + 1] int64


def camera_centres(viewmats: Tensor) -> Tensor:
    """Camera centres ``[B, 3]`` in world from world_to_cam ``[B, 4, 4]``: ``-Rᵀ t``."""
    rot = viewmats[:, :3, :3]
    return -(rot.transpose(-1, -2) @ viewmats[:, :3, 3:]).squeeze(-1)


def make_splats(
    means: Tensor,  # [N, 3]
    quats: Tensor,  # [N, 4]
    scales: Tensor,  # [N, 3]
    opacities: Tensor,  # [N]
    colors: Tensor,  # [N, C] or [N, K, 3] with sh_degree
    viewmats: Tensor,  # [B, 4, 4]
    Ks: Tensor,  # [B, 3, 3]
    width: int,
    height: int,
    *,
    sh_degree: int | None,
    near: float,
    far: float,
    eps2d: float,
    views: Tensor | None = None,  # [N] int: the only camera each Gaussian may be drawn into (-1: none)
    pair_opacity: Callable[[Tensor, Tensor], Tensor] | None = None,
) -> Splats:
    """Cull, sort and project (with grad) the visible pairs; SH colours evaluated per camera.

    ``pair_opacity(camera_ids, gaussian_ids)`` (``[M]`` each), when given, multiplies each pair's
    opacity (a view-dependent fade); pairs it leaves below `MIN_ALPHA` are culled, as a Gaussian
    of that opacity drawn into that camera alone would be."""
    num_cams = viewmats.shape[0]
    with torch.no_grad():
        # Conservative cull without covariances; the exact rule (radii > 0) is applied after projection.
        if views is None:
            maybe = cull_bound(
                means.detach(), scales.detach().amax(-1), viewmats, Ks, width, height, near=near, far=far, eps2d=eps2d
            )
            maybe &= (opacities.detach() >= MIN_ALPHA)[None]  # [B, N]
            cam_ids, gs_ids = maybe.nonzero(as_tuple=True)
        else:  # one camera per Gaussian: only those pairs (listed camera by camera, Gaussians ascending)
            views = views.to(means.device)
            gs_ids = ((views >= 0) & (views < num_cams) & (opacities.detach() >= MIN_ALPHA)).nonzero().squeeze(1)
            gs_ids = gs_ids[torch.sort(views[gs_ids], stable=True).indices]
            cam_ids = views[gs_ids]
            keep = cull_bound_pairs(
                means.detach()[gs_ids],
                scales.detach()[gs_ids].amax(-1),
                viewmats[cam_ids],
                Ks[cam_ids],
                width,
                height,
                near=near,
                far=far,
                eps2d=eps2d,
            )
            cam_ids, gs_ids = cam_ids[keep], gs_ids[keep]
        if pair_opacity is not None:
            faded = opacities.detach()[gs_ids] * pair_opacity(cam_ids, gs_ids).detach()
            keep = faded >= MIN_ALPHA
            cam_ids, gs_ids = cam_ids[keep], gs_ids[keep]
        # Sort key: camera z in float64, so that the order of nearly tied Gaussians (e.g. a
        # fronto-parallel wall, a ground-plane row) does not depend on float32 rounding.
        rot_z = viewmats[:, 2, :3].double()
        z64 = (means.detach()[gs_ids].double() * rot_z[cam_ids]).sum(-1) + viewmats[cam_ids, 2, 3].double()
        counts = torch.bincount(cam_ids, minlength=num_cams)
        offsets = torch.cat([counts.new_zeros(1), counts.cumsum(0)])
        bounds = offsets.tolist()  # nonzero() lists pairs camera by camera, Gaussians ascending
        order = torch.cat([lo + torch.sort(z64[lo:hi], stable=True).indices for lo, hi in zip(bounds[:-1], bounds[1:])])
        cam_ids, gs_ids = cam_ids[order], gs_ids[order]
    covars = covariances_3d(quats, scales)  # [N, 3, 3]
    proj = project_covariances(
        means[gs_ids], covars[gs_ids], viewmats[cam_ids], Ks[cam_ids], width, height, near=near, far=far, eps2d=eps2d
    )
    if sh_degree is None:
        splat_colors = colors[gs_ids]
    else:
        dirs = means[gs_ids] - camera_centres(viewmats)[cam_ids]  # [M, 3]
        splat_colors = sh_to_color(sh_degree, colors[gs_ids], dirs)
    return Splats(
        means2d=proj.means2d,
        conics=proj.conics,
        depths=proj.depths,
        radii=proj.radii,
        opacities=opacities[gs_ids] if pair_opacity is None else opacities[gs_ids] * pair_opacity(cam_ids, gs_ids),
        colors=splat_colors,
        camera_ids=cam_ids,
        gaussian_ids=gs_ids,
        camera_offsets=offsets,
    )
