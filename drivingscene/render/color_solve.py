"""Colours that re-render the input images: a solve over fixed geometry (docs/magnification.md).

Per-pixel Gaussians overlap their neighbours (the footprint rule of ``gaussians.assembly`` makes
sure they do, so that magnified views stay closed), and splatting the input's colours as they are
blurs each image by that overlap: the input views came back like a Gaussian blur of sigma 0.9 px.
With geometry and opacities fixed, an image's own layer (its Gaussians alone, as the layered
blends draw it) is linear in the colours: ``C(p) = sum_i w_i(p) c_i`` with the weights ``w_i``
of its front surface averaged (``render.composite``) and of what lies behind it composited, and the layered blends show it un-premultiplied, ``C / alpha``, where it covers.
``solve_pixel_colors`` finds colours for which that equals the input at every Gaussian's own
pixel, by projected Richardson (Van Cittert) iterations ``c <- clip(c + I(p) - C(p) / alpha(p))``
with the pairs (which Gaussians touch which pixel, in order) found once: the deconvolution of the
splatting blur, exact where depth order makes it irregular.

``solve_pixel_colors`` works on the per-pixel maps before assembly: in its own view a pixel's
Gaussian projects to the pixel centre at its depth, so the splats are built from the maps without
projecting anything. ``solve_gaussian_colors`` works on assembled Gaussians of any geometry, each
standing for a set of its image's pixels (a merged block's, ``gaussians.parsimony``): the splats
are projected into their own image alone (``own_view_splats_of``: what the renderer projects, image
by image without its per-camera cull), and a Gaussian's step is the mean of its pixels' residuals;
a Gaussian standing for its own pixel alone is the per-pixel solve.
"""

from __future__ import annotations

from dataclasses import replace

import torch
from torch import Tensor

from drivingscene import kernels
from drivingscene.errors import InputError
from drivingscene.gaussians.assembly import own_view_covariance
from drivingscene.gaussians.core import SH_C0, Gaussians
from drivingscene.geometry.camera import unproject
from drivingscene.geometry.se3 import matrix_to_quat, matvec, quat_left_matrix
from drivingscene.render.composite import SURFACE_TOLERANCE, composite, find_pairs_torch, pair_inputs
from drivingscene.render.project import EPS2D
from drivingscene.render.rasterize import DEFAULT_MAX_LAYERS, choose_backend
from drivingscene.render.splats import MIN_ALPHA, Splats

# Iterations of the solve: on the DDAD pair the input views went from 27.9 to 32.5 dB after one and
# to ~34 after two (composited); with the smaller cap a third sharpens the magnified views, and more
# add little (docs/magnification.md). Each is a sparse product over pairs found once (~0.01 s).
ITERATIONS = 3
# Colours are kept in [0, MAX_COLOR]: the renderer clamps below 0, and a deconvolution may need a
# little overshoot above white next to dark pixels.
MAX_COLOR = 1.5
# A pixel's residual counts only where its layer covers it at least this much.
MIN_COVERAGE = 0.5


def own_view_splats(
    depth: Tensor,  # [I, H, W] z-depth, metres
    intrinsics: Tensor,  # [I, 3, 3]
    quats: Tensor,  # [I, H, W, 4] w, x, y, z, camera axes
    log_scales: Tensor,  # [I, H, W, 3]
    opacities: Tensor,  # [I, H, W] in (0, 1)
    valid: Tensor,  # [I, H, W] bool: pixels that make a Gaussian
    eps2d: float = EPS2D,
) -> tuple[Splats, Tensor]:
    """Each valid pixel's Gaussian drawn into its own image (as ``rasterize`` would, but without
    projecting: it lands on the pixel centre), in compositing order (image, then depth); and the
    flat pixel index ``[M]`` of each splat. Colours are left empty."""
    num, height, width = depth.shape
    z_map = depth.float().clamp(min=0.0)
    idx = valid.flatten().nonzero().squeeze(1)
    z = z_map.flatten().index_select(0, idx)
    image = idx // (height * width)
    # One sort by (image, depth, pixel): a non-negative float's bits order like the float.
    order = torch.sort((image << 32) | z.view(torch.int32).long(), stable=True).indices
    # index_select: a plain gather, several times faster than advanced indexing on CPU
    idx, z, image = idx.index_select(0, order), z.index_select(0, order), image.index_select(0, order)
    # The footprints on the whole maps (contiguous, focal lengths broadcast), then one gather.
    k = intrinsics.float()
    points = unproject(depth.float().clamp(min=1e-3), k)
    fields = _own_fields(
        points, quats.float(), log_scales.float(), opacities.float(), k[:, None, None, [0, 1], [0, 1]],
        k[:, 0, 1, None, None], eps2d,
    ).reshape(-1, 5).index_select(0, idx)  # fmt: skip
    u = (idx % width).float()
    v = ((idx // width) % height).float()
    return _splats(torch.stack([u, v], -1), fields, z, image, idx, num), idx


def _own_fields(
    points: Tensor, quats: Tensor, log_scales: Tensor, opacities: Tensor, focal: Tensor, skew: Tensor, eps2d: float
) -> Tensor:
    """``[..., 5]``: the conic (3), the 3-sigma radius and the opacity of Gaussians drawn into the
    camera whose axes ``points`` and ``quats`` are given in (`own_view_covariance`, the renderer's
    low-pass added)."""
    a, b, c = own_view_covariance(points, quats, log_scales, focal, skew)
    a, c = a + eps2d, c + eps2d
    det = (a * c - b * b).clamp(min=1e-12)
    largest = 0.5 * (a + c) + torch.sqrt((0.5 * (a - c)) ** 2 + b * b)
    return torch.stack([c / det, -b / det, a / det, 3.0 * torch.sqrt(largest), opacities], -1)


def _splats(means2d: Tensor, fields: Tensor, depths: Tensor, image: Tensor, ids: Tensor, num: int) -> Splats:
    """`Splats` of rows already in compositing order (image, then depth), fields from `_own_fields`."""
    counts = torch.bincount(image, minlength=num)
    return Splats(
        means2d=means2d,
        conics=fields[:, :3],
        depths=depths,
        radii=fields[:, 3],
        opacities=fields[:, 4],
        colors=torch.zeros(len(ids), 3),
        camera_ids=image,
        gaussian_ids=ids,
        camera_offsets=torch.cat([counts.new_zeros(1), counts.cumsum(0)]),
    )


def own_view_splats_of(
    g: Gaussians,
    views: Tensor,  # [N] int64: the image each Gaussian stands in (its pixels')
    world_to_cam: Tensor,  # [I, 4, 4]
    intrinsics: Tensor,  # [I, 3, 3]
    width: int,
    height: int,
    eps2d: float = EPS2D,
    near: float = 0.01,
) -> Splats:
    """Each Gaussian of ``g`` drawn into its own image alone, in compositing order (image, then
    depth): what ``render.splats.make_splats(..., views=views)`` projects, for Gaussians that stand
    on their image's pixels (a per-pixel Gaussian, a merged block), so that its per-camera cull and
    batched products are not needed (0.10 -> 0.04 s on a validation pair's merged Gaussians).
    Gaussians behind ``near`` or fainter than the renderer draws are left out; a splat that misses
    the image gets radius 0. Colours are left empty."""
    num = world_to_cam.shape[0]
    views = views.long()
    ids = torch.arange(len(g), device=views.device)
    sorted_views = len(views) < 2 or bool((views[1:] >= views[:-1]).all())  # as assembled: by image already
    if not sorted_views:
        ids = torch.sort(views, stable=True).indices
        views = views.index_select(0, ids)
    rot, trans = world_to_cam[:, :3, :3].float(), world_to_cam[:, :3, 3].float()
    to_cam = quat_left_matrix(matrix_to_quat(rot))  # [I, 4, 4]: world axes' quaternions to the camera's
    k = intrinsics.float()
    means, quats, log_scales, opacities = g.means.float(), g.quats.float(), g.log_scales.float(), g.opacities.float()
    if not sorted_views:
        means, quats, log_scales, opacities = (x.index_select(0, ids) for x in (means, quats, log_scales, opacities))
    counts = torch.bincount(views, minlength=num).tolist()
    parts, lo = [], 0
    for b, n in enumerate(counts):  # image by image, its matrices broadcast: no [N, 3, 3] gather
        if n == 0:
            continue
        p_cam = matvec(rot[b], means[lo : lo + n], trans[b])
        z = p_cam[:, 2].clamp(min=near)
        x, y = p_cam[:, 0] / z, p_cam[:, 1] / z
        fields = _own_fields(
            p_cam, matvec(to_cam[b], quats[lo : lo + n]), log_scales[lo : lo + n], opacities[lo : lo + n],
            k[b, [0, 1], [0, 1]], k[b, 0, 1], eps2d,
        )  # fmt: skip
        u, v = k[b, 0, 0] * x + k[b, 0, 1] * y + k[b, 0, 2], k[b, 1, 1] * y + k[b, 1, 2]
        radius = fields[:, 3]
        touches = (u + radius >= 0) & (u - radius <= width - 1) & (v + radius >= 0) & (v - radius <= height - 1)
        fields[:, 3] = torch.where(touches, radius, 0.0)
        parts.append(torch.cat([fields, u[:, None], v[:, None], p_cam[:, 2:]], -1))
        lo += n
    rows = torch.cat([torch.zeros(0, 8), *parts])  # [N, 8]: conic, radius, opacity, u, v, z
    z = rows[:, 7]
    keep = ((z >= near) & (rows[:, 4] >= MIN_ALPHA)).nonzero().squeeze(1)
    # one sort by (image, depth, Gaussian): a positive float's bits order like the float
    key = (views.index_select(0, keep) << 32) | z.index_select(0, keep).view(torch.int32).long()
    order = keep.index_select(0, torch.sort(key, stable=True).indices)
    rows = rows.index_select(0, order)
    return _splats(rows[:, 5:7], rows[:, :5], rows[:, 7], views.index_select(0, order), ids.index_select(0, order), num)


def solve_pixel_colors(
    depth: Tensor,  # [I, H, W] z-depth, metres (one map per input image)
    intrinsics: Tensor,  # [I, 3, 3]
    quats: Tensor,  # [I, H, W, 4] camera axes
    log_scales: Tensor,  # [I, H, W, 3] as assembled (after the footprint rule)
    opacities: Tensor,  # [I, H, W] in (0, 1)
    colors: Tensor,  # [I, H, W, 3] the starting colours
    images: Tensor,  # [I, H, W, 3] what each image's own layer should re-render, in [0, 1]
    valid: Tensor,  # [I, H, W] bool: pixels that make a Gaussian
    iterations: int = ITERATIONS,
    eps2d: float = EPS2D,
    backend: str = "auto",
    surface_tolerance: float = SURFACE_TOLERANCE,
) -> Tensor:
    """Colours ``[I, H, W, 3]`` for which each image's own layer re-renders ``images`` (module
    docstring); unchanged at pixels that make no Gaussian. ``surface_tolerance``: the own layer's
    rule (the layered blends' `LayerBlend.surface_tolerance`). No gradients."""
    if images.shape != colors.shape or images.shape[:3] != depth.shape or images.shape[-1] != 3:
        raise InputError(
            f"solve_pixel_colors: colors and images must be [I, H, W, 3] matching depth {list(depth.shape)}, "
            f"found {list(colors.shape)} and {list(images.shape)}"
        )
    if iterations <= 0 or not bool(valid.any()):
        return colors
    height, width = depth.shape[1:]
    with torch.no_grad():
        splats, pixel = own_view_splats(depth, intrinsics, quats, log_scales, opacities, valid, eps2d)
        solved = _solve_splats(
            splats, width, height, torch.arange(len(pixel) + 1), pixel, images.reshape(-1, 3).float(),
            colors.reshape(-1, 3).float().index_select(0, pixel), iterations, surface_tolerance,
            choose_backend(backend, depth) == "cpp",
        )  # fmt: skip
        out = colors.reshape(-1, 3).clone()
        out.index_copy_(0, pixel, solved.to(out.dtype))
    return out.reshape(colors.shape)


def _solve_splats(
    splats: Splats,
    width: int,
    height: int,
    member_offsets: Tensor,  # [M + 1]: splat i stands for members[member_offsets[i]:member_offsets[i + 1]]
    members: Tensor,  # [K] flat pixel indices into the images
    target: Tensor,  # [I * H * W, 3] what each pixel should render
    start: Tensor,  # [M, 3] the splats' starting colours
    iterations: int,
    surface_tolerance: float,
    compiled: bool,
) -> Tensor:
    """The solve over the splats' own layers (module docstring): their colours ``[M, 3]``, each
    moved by the mean residual over the pixels it stands for. Compiled: pairs and weights formed
    once, then sparse products (`kernels.own_layer_solve`); else the reference, a compositing pass
    per step."""
    inp = pair_inputs(splats, width, height)
    if compiled:
        return kernels.own_layer_solve(
            inp.means2d.float().contiguous(), inp.conics.float().contiguous(), inp.opacities.float().contiguous(),
            inp.sigma_max.float().contiguous(), inp.boxes, inp.camera_offsets, width, height, DEFAULT_MAX_LAYERS,
            splats.depths.float().contiguous(), member_offsets, members, target, start.contiguous(), iterations,
            surface_tolerance, MAX_COLOR, MIN_COVERAGE,
        )  # fmt: skip
    pair_ids = find_pairs_torch(inp, width, height, DEFAULT_MAX_LAYERS)
    member_counts = member_offsets[1:] - member_offsets[:-1]
    row_of_member = torch.repeat_interleave(torch.arange(len(start)), member_counts)
    member_target = target.index_select(0, members)
    solved = start.clamp(0.0, MAX_COLOR)
    black = torch.zeros(len(splats.camera_offsets) - 1, 3)
    for _ in range(iterations):
        rgb, _, alpha = composite(
            pair_ids, inp.means2d, inp.conics, inp.opacities, splats.depths, solved, black, width, height, False,
            surface_tolerance,
        )  # fmt: skip
        rgb, alpha = rgb.reshape(-1, 3).index_select(0, members), alpha.reshape(-1).index_select(0, members)
        defined = (alpha >= MIN_COVERAGE).float()
        residual = (member_target - rgb / alpha.clamp(min=1e-6)[:, None]) * defined[:, None]
        total = torch.zeros_like(solved).index_add_(0, row_of_member, residual)
        count = torch.zeros(len(solved)).index_add_(0, row_of_member, defined)
        solved = (solved + total / count.clamp(min=1)[:, None]).clamp(0.0, MAX_COLOR)
    return solved


def solve_gaussian_colors(
    g: Gaussians,
    owners: Tensor,  # [P] int64: the Gaussian of ``g`` each of the pixels stands in (`merge_blocks`' owners)
    pixels: Tensor,  # [P] int64: those pixels, flat indices into the images [I, H, W]
    images: Tensor,  # [I, H, W, 3] in [0, 1]: image keyframe * V + camera of the Gaussians
    world_to_cam: Tensor,  # [I, 4, 4] each image's camera
    intrinsics: Tensor,  # [I, 3, 3]
    iterations: int = ITERATIONS,
    eps2d: float = EPS2D,
    backend: str = "auto",
    surface_tolerance: float = SURFACE_TOLERANCE,
) -> Gaussians:
    """``g`` with its view-independent colours solved so that each image's own layer re-renders the
    image, a Gaussian fitted over all the pixels it stands for (a merged block's: the mean of their
    residuals, module docstring), after `merge_blocks` or any other change of the geometry: the
    splats are projected (`own_view_splats_of`), not built from the maps. The SH terms above the DC
    are kept. No gradients."""
    num, height, width = images.shape[:3]
    if images.shape[-1] != 3 or owners.shape != pixels.shape or world_to_cam.shape[0] != num or intrinsics.shape[0] != num:
        raise InputError(
            f"solve_gaussian_colors: expected images [I, H, W, 3] with I cameras and intrinsics, owners and pixels [P], found "
            f"images {list(images.shape)}, world_to_cam {list(world_to_cam.shape)}, intrinsics {list(intrinsics.shape)}, "
            f"owners {list(owners.shape)}, pixels {list(pixels.shape)}"
        )
    if iterations <= 0 or len(g) == 0:
        return g
    with torch.no_grad():
        start = (SH_C0 * g.sh[:, 0].float() + 0.5).clamp(min=0.0)
        views = g.keyframes.long() * (num // 2) + g.cameras.long()
        s = own_view_splats_of(g, views, world_to_cam, intrinsics, width, height, eps2d)
        gids = s.gaussian_ids
        # each splat's pixels, in splat order (CSR)
        counts = torch.bincount(owners, minlength=len(g))
        by_owner = pixels.index_select(0, torch.sort(owners, stable=True).indices)
        owner_start = torch.cumsum(counts, 0) - counts
        row_counts = counts.index_select(0, gids)
        offsets = torch.cat([row_counts.new_zeros(1), torch.cumsum(row_counts, 0)])
        total = int(offsets[-1])
        within = torch.arange(total) - torch.repeat_interleave(offsets[:-1], row_counts)
        members = by_owner.index_select(0, torch.repeat_interleave(owner_start.index_select(0, gids), row_counts) + within)
        colors = start.index_select(0, gids)
        solved = _solve_splats(
            s, width, height, offsets, members, images.reshape(-1, 3).float(), colors, iterations, surface_tolerance,
            choose_backend(backend, g.means) == "cpp",
        )  # fmt: skip
        change = torch.zeros_like(start)
        change.index_copy_(0, gids, solved - colors)
        sh = g.sh.clone()
        sh[:, 0] = sh[:, 0] + (change / SH_C0).to(sh.dtype)
    return replace(g, sh=sh)
