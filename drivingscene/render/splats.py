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
from dataclasses import dataclass, fields

import torch
from torch import Tensor

from drivingscene.render.project import Projection, covariances_3d, cull_bound, project_covariances
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


def _camera_offsets(cam_ids: Tensor, num_cams: int) -> tuple[Tensor, list[int]]:
    """Row offsets ``[B + 1]`` of pairs grouped by camera (``cam_ids`` ``[M]`` ascending), and as a list."""
    counts = torch.bincount(cam_ids, minlength=num_cams)
    offsets = torch.cat([counts.new_zeros(1), counts.cumsum(0)])
    return offsets, offsets.tolist()


def _by_camera(bounds: list[int], fn: Callable[[int, int, int], Tensor | Projection]) -> list:
    """``fn(b, lo, hi)`` for each camera ``b`` whose pairs are rows ``lo:hi`` (none: skipped)."""
    return [fn(b, lo, hi) for b, (lo, hi) in enumerate(zip(bounds[:-1], bounds[1:])) if hi > lo]


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
            cam_ids = views.index_select(0, gs_ids)
            if len(cam_ids) > 1 and not bool((cam_ids[1:] >= cam_ids[:-1]).all()):  # already by camera: no sort
                by_camera = torch.sort(cam_ids, stable=True).indices
                gs_ids, cam_ids = gs_ids.index_select(0, by_camera), cam_ids.index_select(0, by_camera)
            # camera by camera (cull_bound of one camera), not one gathered [M, 4, 4] matrix per pair
            pair_means = means.detach().index_select(0, gs_ids)
            pair_scales = scales.detach().index_select(0, gs_ids).amax(-1)
            culled = _by_camera(
                _camera_offsets(cam_ids, num_cams)[1],
                lambda b, lo, hi: cull_bound(
                    pair_means[lo:hi], pair_scales[lo:hi], viewmats[b : b + 1], Ks[b : b + 1], width, height,
                    near=near, far=far, eps2d=eps2d,
                )[0],
            )  # fmt: skip
            keep = torch.cat([pair_scales.new_zeros(0, dtype=torch.bool), *culled])
            keep = keep.nonzero().squeeze(1)
            cam_ids, gs_ids = cam_ids.index_select(0, keep), gs_ids.index_select(0, keep)
        if pair_opacity is not None:
            faded = opacities.detach()[gs_ids] * pair_opacity(cam_ids, gs_ids).detach()
            keep = faded >= MIN_ALPHA
            cam_ids, gs_ids = cam_ids[keep], gs_ids[keep]
        # Sort key: camera z in float64, so that the order of nearly tied Gaussians (e.g. a
        # fronto-parallel wall, a ground-plane row) does not depend on float32 rounding.
        rot_z, t_z = viewmats[:, 2, :3].double(), viewmats[:, 2, 3].double()
        z64 = (means.detach().index_select(0, gs_ids).double() * rot_z.index_select(0, cam_ids)).sum(-1)
        z64 = z64 + t_z.index_select(0, cam_ids)
        offsets, bounds = _camera_offsets(cam_ids, num_cams)  # nonzero() lists pairs camera by camera, Gaussians ascending
        order = torch.cat([lo + torch.sort(z64[lo:hi], stable=True).indices for lo, hi in zip(bounds[:-1], bounds[1:])])
        cam_ids, gs_ids = cam_ids.index_select(0, order), gs_ids.index_select(0, order)
    # index_select: a plain gather (and its backward an index_add), several times faster than
    # advanced indexing on a CPU
    covars = covariances_3d(quats, scales)  # [N, 3, 3]
    pair_means, pair_covars = means.index_select(0, gs_ids), covars.index_select(0, gs_ids)
    # camera by camera (the pairs are grouped by camera), its matrices broadcast rather than
    # gathered into one [M, 4, 4] copy per pair
    parts = _by_camera(
        bounds,
        lambda b, lo, hi: project_covariances(
            pair_means[lo:hi], pair_covars[lo:hi], viewmats[b : b + 1], Ks[b : b + 1], width, height,
            near=near, far=far, eps2d=eps2d,
        ),
    )  # fmt: skip
    if len(parts) == 1:
        proj = parts[0]
    elif parts:
        proj = Projection(*(torch.cat([getattr(p, f.name) for p in parts]) for f in fields(Projection)))
    else:  # no pair: the empty fields, shaped as the projection makes them
        proj = project_covariances(pair_means, pair_covars, viewmats[:1], Ks[:1], width, height, near=near, far=far, eps2d=eps2d)
    if sh_degree is None:
        splat_colors = colors.index_select(0, gs_ids)
    else:
        dirs = means.index_select(0, gs_ids) - camera_centres(viewmats).index_select(0, cam_ids)  # [M, 3]
        splat_colors = sh_to_color(sh_degree, colors.index_select(0, gs_ids), dirs)
    pair_opacities = opacities.index_select(0, gs_ids)
    if pair_opacity is not None:
        pair_opacities = pair_opacities * pair_opacity(cam_ids, gs_ids)
    return Splats(
        means2d=proj.means2d,
        conics=proj.conics,
        depths=proj.depths,
        radii=proj.radii,
        opacities=pair_opacities,
        colors=splat_colors,
        camera_ids=cam_ids,
        gaussian_ids=gs_ids,
        camera_offsets=offsets,
    )
