"""No more Gaussians than an image needs: per-pixel Gaussians merged into blocks where one does.

Per-pixel assembly gives every input pixel a Gaussian, whatever the pixel shows. Where a 2x2 block
of an image's pixels is one flat piece of surface whose colour the merged splats can draw and
that moves as one, four Gaussians draw what one Gaussian twice their size draws: the block's
Gaussians become one, at their mean, with their mean colour, opacity and flow, and their shape
scaled by the block's side (2: the pixel grid of the block's Gaussians is twice as coarse, so a
merged Gaussian overlaps its neighbours as a per-pixel one does and the surface stays closed at
any magnification). Repeated on the merged blocks (``levels`` > 1), flat regions (road, walls,
sky at the far layer) end up with one Gaussian per 4x4 pixels.

A block merges only when its Gaussians are all there (no sky, no ego body, none carved), come
from one image, are all view-bound or none, agree in colour (``color_test``: by default no pixel
is more than ``color_range`` from the block means interpolated bilinearly, what the merged,
overlapping splats draw between their centres, so a smooth gradient merges and texture does not;
or the block's range of a channel), lie on one plane (the block's depths span at most
``depth_range`` of their mean and are bilinear within ``planarity`` of it: a depth edge or a fold
is not merged) and move alike (flows within ``flow_range`` metres): nothing that moves is merged
with what does not, and a merged Gaussian keeps its image's layer (keyframe and camera), so the
layered blends draw it as before. With ``fit_colors`` the reconstruction then solves every
Gaussian's colour over the pixels it stands for (`render.color_solve.solve_gaussian_colors`,
``merge_blocks(..., with_owners=True)`` says which), in place of the per-pixel solve, and the colour
test reads the input images sharpened as that solve will (`sharpened`). The thresholds were chosen
on validation pairs (docs/parsimony.md); the per-pixel output stays selectable
(``InferenceOptions.merge = None``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace

import torch
import torch.nn.functional as F
from torch import Tensor

from drivingscene.gaussians.core import Gaussians, sh0_to_rgb
from drivingscene.geometry.camera import project, unproject


@dataclass(frozen=True)
class BlockMerge:
    """When a 2x2 block of Gaussians becomes one (module docstring)."""

    color_range: float = 0.045  # in [0, 1]: the largest colour difference ``color_test`` allows
    planarity: float = 0.03  # |d00 + d11 - d01 - d10| / mean depth
    depth_range: float = 0.1  # (largest - smallest depth) / mean depth: a depth edge is not merged
    flow_range: float = 0.05  # metres: largest range of a flow component in the block
    levels: int = 1  # 1: 2x2 blocks only; 2: merged blocks merge again into 4x4
    # What ``color_range`` bounds: "range", the block's largest range of a channel; "detail", how far
    # a pixel's colour is from the block means interpolated bilinearly (what the merged, overlapping
    # splats draw there: a smooth gradient merges, texture does not)
    color_test: str = "detail"
    # Iterations of the colour solve over the merged Gaussians (render.color_solve,
    # `solve_gaussian_colors`: a merged Gaussian fitted over its block's pixels), in place of the
    # per-pixel solve; the colour test then reads the input images sharpened (`sharpened`: the
    # colours are not solved yet). 0: the per-pixel solve, the test on its colours, and each merged
    # Gaussian the mean of its block's (the default of 2026-12-01, docs/parsimony.md).
    fit_colors: int = 3
    # A budget: at most this share of the per-pixel Gaussians (`merge_to_budget`); None: the thresholds
    # above decide alone.
    budget: float | None = None

    def __post_init__(self):
        from drivingscene.errors import InputError

        if self.levels < 1 or self.fit_colors < 0 or min(self.color_range, self.planarity, self.depth_range, self.flow_range) < 0:
            raise InputError(f"BlockMerge: expected levels >= 1, fit_colors >= 0 and non-negative thresholds, found {self}")
        if self.color_test not in ("range", "detail"):
            raise InputError(f"BlockMerge.color_test: expected 'range' or 'detail', found {self.color_test!r}")
        if self.budget is not None and not 0 < self.budget <= 1:
            raise InputError(f"BlockMerge.budget: expected a share of the per-pixel Gaussians in (0, 1], found {self.budget}")


# `sharpened`: an unsharp mask, about what the colour solve's deconvolution of the splats' overlap
# makes of an image (chosen on validation pairs, docs/parsimony.md)
SHARPEN_SIGMA = 0.8  # px
SHARPEN_AMOUNT = 1.0


def sharpened(images: Tensor) -> Tensor:
    """``[I, H, W, 3]`` images in [0, 1], unsharp-masked: ``I + SHARPEN_AMOUNT (I - blur(I))``, a
    Gaussian blur of ``SHARPEN_SIGMA`` px (5x5, borders replicated). What the merge's colour test
    reads when the colours are solved after it."""
    import cv2
    import numpy as np

    x = images.detach().float().cpu().numpy()
    blur = np.stack([cv2.GaussianBlur(im, (5, 5), SHARPEN_SIGMA, borderType=cv2.BORDER_REPLICATE) for im in x])
    return torch.from_numpy(x + SHARPEN_AMOUNT * (x - blur)).to(images.device)


def _blocks(x: Tensor) -> Tensor:
    """``[I, H, W, ...]`` -> ``[I, H // 2, W // 2, 4, ...]``: each 2x2 block's four entries (row-major;
    an odd last row or column is left out)."""
    num, height, width = x.shape[:3]
    x = x[:, : height // 2 * 2, : width // 2 * 2]
    tail = x.shape[3:]
    x = x.reshape(num, height // 2, 2, width // 2, 2, *tail).transpose(2, 3)
    return x.reshape(num, height // 2, width // 2, 4, *tail)


def _block_sums(x: Tensor) -> Tensor:
    """``[I, H, W, ...]`` -> ``[I, H // 2, W // 2, ...]``: each 2x2 block's sum (`_blocks` summed,
    without its copy)."""
    num, height, width = x.shape[:3]
    x = x[:, : height // 2 * 2, : width // 2 * 2]
    return x.reshape(num, height // 2, 2, width // 2, 2, *x.shape[3:]).sum((2, 4))


def _detail(rgb: Tensor, ids: Tensor) -> Tensor:
    """``[I, h, w]``: each 2x2 block's largest difference (over its pixels and the channels) between
    a pixel's colour and the block means interpolated bilinearly at that pixel, over the blocks
    that hold Gaussians (weights normalised: no Gaussian, no weight)."""
    has = (ids >= 0).to(rgb.dtype)
    # one gather over every pixel (no Gaussian: any row, zeroed), not a masked scatter
    cmap = rgb.index_select(0, ids.clamp(min=0).flatten()).view(*ids.shape, 3) * has[..., None]
    weight = _block_sums(has)  # [I, h, w]
    means = _block_sums(cmap)  # [I, h, w, 3] sums
    stack = torch.cat([means, weight[..., None]], -1).permute(0, 3, 1, 2)
    up = F.interpolate(stack, scale_factor=2, mode="bilinear", align_corners=False).permute(0, 2, 3, 1)
    smooth = up[..., :3] / up[..., 3:].clamp(min=1e-6)
    crop = cmap[:, : smooth.shape[1], : smooth.shape[2]]
    return _blocks((crop - smooth).abs().amax(-1)).amax(-1)


@dataclass(frozen=True)
class _Level:
    """What a level's tests read: the id map ``[I, H, W]`` of the current Gaussians (-1: none),
    their depth map, and per Gaussian ``[n, ...]`` the colours for the colour test, the flows and
    whether they are view-bound."""

    ids: Tensor
    depth: Tensor
    rgb: Tensor
    flows: Tensor
    bound: Tensor
    detail: Tensor | None = None  # `_detail` of ``rgb`` over ``ids``, when known (the first level's, kept over a budget's tries)


def _first_level(g: Gaussians, pixels: Tensor, depth: Tensor, colors: Tensor | None, config: BlockMerge) -> _Level:
    num, height, width = depth.shape
    ids = torch.full((num * height * width,), -1, dtype=torch.long, device=pixels.device)
    ids[pixels] = torch.arange(len(g), device=pixels.device)
    rgb = sh0_to_rgb(g.sh[:, 0]) if colors is None else colors.to(g.sh)
    ids = ids.view(num, height, width)
    return _Level(ids, depth.float(), rgb, g.flows, g.view_bound, _detail(rgb, ids) if config.color_test == "detail" else None)


def _decide(level: _Level, config: BlockMerge, following: bool = True) -> tuple[Tensor, Tensor, Tensor, _Level | None]:
    """Which blocks of ``level`` merge: their ids ``[M, 4]``, their flat indices into the blocks
    ``[I, h, w]``, their mean depths ``[M]``, and, when ``following``, the next level's tests (its
    id map into the merged ones, -1 where a block did not merge; its depth map; the merged blocks'
    mean colours and flows; None otherwise)."""
    block_ids = _blocks(level.ids)  # [I, h, w, 4]
    block_depth = _blocks(level.depth)
    full = (block_ids >= 0).all(-1)
    # flat indices and index_select throughout: plain gathers, several times faster on a CPU than
    # boolean indexing
    full_at = full.flatten().nonzero().squeeze(1)  # [C]
    cand = block_ids.reshape(-1, 4).index_select(0, full_at)  # [C, 4]
    d = block_depth.reshape(-1, 4).index_select(0, full_at)
    mean_depth = d.mean(-1)
    planar = ((d[:, 0] + d[:, 3] - d[:, 1] - d[:, 2]).abs() <= config.planarity * mean_depth) & (
        d.amax(-1) - d.amin(-1) <= config.depth_range * mean_depth
    )
    flat_cand = cand.flatten()
    if config.color_test == "detail":
        detail = _detail(level.rgb, level.ids) if level.detail is None else level.detail
        color_ok = detail.flatten().index_select(0, full_at) <= config.color_range
    else:
        rgb = level.rgb.index_select(0, flat_cand).view(-1, 4, 3)
        color_ok = (rgb.amax(1) - rgb.amin(1)).amax(-1) <= config.color_range
    flows = level.flows.index_select(0, flat_cand).view(-1, 4, 3)
    bound = level.bound.index_select(0, flat_cand).view(-1, 4)
    ok = planar & color_ok & ((flows.amax(1) - flows.amin(1)).amax(-1) <= config.flow_range) & (bound.all(-1) | ~bound.any(-1))
    ok_at = ok.nonzero().squeeze(1)
    groups = cand.index_select(0, ok_at)  # [M, 4]
    merged_at = full_at.index_select(0, ok_at)
    if not following:
        return groups, merged_at, mean_depth.index_select(0, ok_at), None
    next_ids = torch.full(block_ids.shape[:3], -1, dtype=torch.long, device=level.ids.device)
    next_ids.view(-1).index_copy_(0, merged_at, torch.arange(len(groups), device=level.ids.device))
    flat = groups.flatten()
    next_level = _Level(
        next_ids,
        block_depth.mean(-1),
        _group_mean(level.rgb, flat),
        _group_mean(level.flows, flat),
        level.bound.index_select(0, groups[:, 0]),
    )
    return groups, merged_at, mean_depth.index_select(0, ok_at), next_level


def _group_mean(x: Tensor, flat: Tensor) -> Tensor:
    """``[M, ...]``: the mean of ``x`` ``[n, ...]`` over each group of four of the flat ids ``[4 M]``."""
    return x.index_select(0, flat).view(len(flat) // 4, 4, *x.shape[1:]).mean(1)


def _merged_gaussians(
    g: Gaussians, groups: Tensor, merged_at: Tensor, mean_depth: Tensor, blocks_per_image: int, focal: Tensor,
    side: float, eps2d: float,
) -> Gaussians:  # fmt: skip
    """The Gaussians ``groups`` ``[M, 4]`` of ``g`` merge into (module docstring): their mean,
    colour, opacity and flow, their shape scaled by ``side``."""
    flat = groups.flatten()
    first = groups[:, 0]
    # The renderer adds its low-pass ``eps2d`` (px^2) to every splat: scaling the 3D shape by ``side``
    # scales the splat's own variance by side^2 but not the low-pass, so (side^2 - 1) eps2d more,
    # isotropic at the block's depth, make the merged splat exactly ``side`` times a pixel's.
    image = merged_at // blocks_per_image  # [M] each block's image
    low_pass = (side**2 - 1) * eps2d * (mean_depth / focal.to(mean_depth).index_select(0, image)) ** 2  # m^2
    log_scales = 0.5 * torch.log(torch.exp(2 * (_group_mean(g.log_scales, flat) + math.log(side))) + low_pass[:, None])
    return Gaussians(
        means=_group_mean(g.means, flat),
        quats=g.quats.index_select(0, first),
        log_scales=log_scales,
        opacity_logits=torch.logit(_group_mean(g.opacities[:, None], flat)[:, 0].clamp(1e-6, 1 - 1e-6)),
        sh=_group_mean(g.sh, flat),
        flows=_group_mean(g.flows, flat),
        keyframes=g.keyframes.index_select(0, first),
        cameras=g.cameras.index_select(0, first),
        view_rays=F.normalize(_group_mean(g.view_rays, flat), dim=-1),  # zero stays zero
    )


def _merged_count(level: _Level, config: BlockMerge) -> int:
    """How many Gaussians `merge_blocks` leaves, from the tests alone (no Gaussian is built): each
    block that merges turns four into one."""
    count = int((level.ids >= 0).sum())
    for step in range(config.levels):
        if min(level.depth.shape[1:]) < 2:
            break
        groups, _, _, level = _decide(level, config, following=step + 1 < config.levels)
        count -= 3 * len(groups)
        if len(groups) == 0:
            break
    return count


def merge_blocks(
    g: Gaussians,
    pixels: Tensor,  # [N] int64: each Gaussian's flat pixel index into [I, H, W] (image-major)
    depth: Tensor,  # [I, H, W] z-depth of every image (metres)
    intrinsics: Tensor,  # [I, 3, 3]
    config: BlockMerge = BlockMerge(),
    *,
    eps2d: float,  # the renderer's low-pass, px^2 (render.project.EPS2D)
    with_owners: bool = False,
    colors: Tensor | None = None,  # [N, 3] the colours the colour test reads; None: the Gaussians' own (DC)
) -> Gaussians | tuple[Gaussians, Tensor]:
    """``g`` with the blocks that qualify merged (module docstring), ordered by image (keyframe,
    then camera) as assembled: merged Gaussians follow their image's remaining per-pixel ones.
    ``with_owners``: also ``[N]`` int64, the output Gaussian each of ``g`` became (itself or the
    block it merged into), so that a merged Gaussian's pixels are known (`render.color_solve`)."""
    focal = 0.5 * (intrinsics[:, 0, 0] + intrinsics[:, 1, 1]).float()  # [I] pixels per metre at 1 m
    level = _first_level(g, pixels, depth, colors, config)
    current, parts = g, []
    # each input Gaussian's place: in the current level (label) until it lands in a part (owner);
    # whole-array selects (torch.where and gathers), not boolean indexing, which is several times slower
    label = torch.arange(len(g), device=g.device)
    owner = torch.full((len(g),), -1, dtype=torch.long, device=g.device)
    placed = 0
    for step in range(config.levels):
        if min(level.depth.shape[1:]) < 2:
            break
        blocks_per_image = (level.depth.shape[1] // 2) * (level.depth.shape[2] // 2)
        groups, merged_at, mean_depth, level = _decide(level, config, following=step + 1 < config.levels)
        merged = _merged_gaussians(current, groups, merged_at, mean_depth, blocks_per_image, focal * 0.5**step, 2.0, eps2d)
        alive = torch.ones(len(current), dtype=torch.bool, device=g.device)  # the previous level's that merged give way
        flat = groups.flatten()
        alive[flat] = False
        rank = torch.cumsum(alive, 0) - 1
        group_of = torch.full((len(current),), -1, dtype=torch.long, device=g.device)
        group_of[flat] = torch.arange(len(groups), device=g.device).repeat_interleave(4)
        pending = owner < 0  # not placed yet: label is into `current`
        at = torch.where(pending, label, 0)
        stays = alive.index_select(0, at)
        owner = torch.where(pending & stays, placed + rank.index_select(0, at), owner)
        label = torch.where(pending & ~stays, group_of.index_select(0, at), label)
        placed += int(alive.sum())
        parts.append(current.index(alive))
        current = merged
        if len(merged) == 0:
            break
    owner = torch.where(owner < 0, placed + label, owner)
    parts.append(current)
    # ordered by image (keyframe, then camera) as assembled: the i-th Gaussian of the parts'
    # concatenation goes to position[i], each field copied from its part straight into its place
    # (no concatenation, then no reordered copy of it)
    cameras = torch.cat([part.cameras for part in parts])
    image = torch.cat([part.keyframes for part in parts]) * (int(cameras.max()) + 1 if len(cameras) else 1) + cameras
    order = torch.sort(image, stable=True).indices
    position = torch.empty_like(order)
    position[order] = torch.arange(len(order), device=order.device)
    places = position.split([len(part) for part in parts])
    fields_out = {}
    for f in fields(Gaussians):
        first = getattr(parts[0], f.name)
        fields_out[f.name] = first.new_empty((len(order), *first.shape[1:]))
        for part, where in zip(parts, places):
            fields_out[f.name].index_copy_(0, where, getattr(part, f.name))
    out = Gaussians(**fields_out)
    if not with_owners:
        return out
    return out, position.index_select(0, owner)


@dataclass(frozen=True)
class KeyframeDedupe:
    """When a static pixel's Gaussian is left to the other keyframe's image of the same camera
    (`keyframe_duplicates`)."""

    depth_tolerance: float = 0.03  # relative: the other image's depth where the point lands
    color_tolerance: float = 0.03  # mean absolute RGB difference over a 3x3 window, in [0, 1]
    finer: float = 0.95  # keyframe 0 gives way only where keyframe 1 is this much nearer (finer)


def keyframe_duplicates(
    depth: Tensor,  # [2, V, H, W] z-depth
    static: Tensor,  # [2, V, H, W] bool: pixels whose Gaussian exists and does not move
    images: Tensor,  # [2, V, 3, H, W] in [0, 1]
    cam_to_world: Tensor,  # [2, V, 4, 4] (any common frame)
    intrinsics: Tensor,  # [V, 3, 3]
    config: KeyframeDedupe = KeyframeDedupe(),
) -> Tensor:
    """``[2, V, H, W]`` bool: static pixels whose surface point the same camera's image at the other
    keyframe also holds (it lands inside that image on a static pixel at the same depth within
    ``depth_tolerance`` and the same colours over a 3x3 window), and samples at least as finely
    (keyframe 0's point given way only where keyframe 1 sees it ``finer`` times nearer, so that of
    two copies one stays): the Gaussians one of the two copies makes redundant."""
    _, num_views, height, width = depth.shape
    k = intrinsics.float()
    out = torch.zeros_like(static)
    for key in (0, 1):
        other = 1 - key
        points = unproject(depth[key].float().clamp(min=1e-3), k)  # [V, H, W, 3] camera axes
        rel = (torch.linalg.inv(cam_to_world[other].double()) @ cam_to_world[key].double()).float()
        q = torch.einsum("vij,vhwj->vhwi", rel[:, :3, :3], points) + rel[:, None, None, :3, 3]
        uv, z_there = project(q.flatten(1, 2), k, eps=1e-3)
        uv, z_there = uv.view(num_views, height, width, 2), z_there.view(num_views, height, width)
        z = z_there.clamp(min=1e-3)
        size = torch.tensor([width, height], dtype=uv.dtype, device=uv.device)
        grid = (uv + 0.5) / size * 2 - 1
        inside = (grid.abs() <= 1).all(-1) & (z_there > 1e-2)
        there = F.grid_sample(
            torch.cat([depth[other].float()[:, None], static[other].float()[:, None]], 1), grid, mode="nearest",
            align_corners=False,
        )  # fmt: skip
        warped = F.grid_sample(images[other].float(), grid, mode="bilinear", align_corners=False)
        diff = F.avg_pool2d((warped - images[key].float()).abs().mean(1, keepdim=True), 3, 1, 1, count_include_pad=False)[:, 0]
        agree = (
            inside
            & static[key]
            & (there[:, 1] > 0.5)
            & ((z - there[:, 0]).abs() <= config.depth_tolerance * there[:, 0])
            & (diff <= config.color_tolerance)
        )
        finer = z <= depth[key] * (1.0 if key == 1 else config.finer)
        out[key] = agree & finer
    return out


# `merge_to_budget`: the most levels of merging it tries, the bisection steps on the colour range
# (and on the geometry tests' factor), and the most the depth tests are loosened where colour alone
# cannot meet a budget.
BUDGET_LEVELS = 3
BUDGET_STEPS = 6
BUDGET_GEOMETRY = 4.0  # depth range 0.4, planarity 0.12: a larger depth step never merges


def merge_to_budget(
    g: Gaussians,
    pixels: Tensor,
    depth: Tensor,
    intrinsics: Tensor,
    config: BlockMerge,
    *,
    eps2d: float,
    with_owners: bool = False,
    colors: Tensor | None = None,
) -> Gaussians | tuple[Gaussians, Tensor]:
    """`merge_blocks` that meets ``config.budget`` (a share of ``len(g)``, the per-pixel Gaussians).

    In order, the first that meets it: the configured merge; with the fewest levels (up to
    `BUDGET_LEVELS`) at which merging blocks of any colour does, the smallest colour range that
    meets it (bisection, `BUDGET_STEPS` merges); with `BUDGET_LEVELS` levels and any colour, the
    smallest factor (up to `BUDGET_GEOMETRY`) on the planarity and depth-range tests that meets it
    (bisection), so that the blocks across the smallest depth steps merge first. Past that, a depth
    edge is never merged (it would leave a Gaussian floating between the two surfaces), nor are
    moving and static content: where those alone hold more than the budget it is not met, and the
    result is the fewest Gaussians reached. ``with_owners``, ``colors``: as `merge_blocks`."""
    if config.budget is None:
        return merge_blocks(g, pixels, depth, intrinsics, config, eps2d=eps2d, with_owners=with_owners, colors=colors)
    target = config.budget * len(g)
    first = _first_level(g, pixels, depth, colors, config)

    def loosened(color_range: float, levels: int, geometry: float = 1.0) -> BlockMerge:
        return replace(
            config,
            color_range=color_range,
            levels=levels,
            planarity=config.planarity * geometry,
            depth_range=config.depth_range * geometry,
        )

    sizes: dict[BlockMerge, int] = {}

    def size(setting: BlockMerge) -> int:  # from the tests alone: the Gaussians are built once, at the end
        if setting not in sizes:
            sizes[setting] = _merged_count(first, setting)
        return sizes[setting]

    def bisect(lo: float, hi: float, candidate) -> BlockMerge:
        """The smallest parameter in ``[lo, hi]`` (geometric bisection) whose merge meets the target;
        the merge at ``hi`` does."""
        best = candidate(hi)
        for _ in range(BUDGET_STEPS):
            mid = math.sqrt(lo * hi)
            setting = candidate(mid)
            if size(setting) <= target:
                hi, best = mid, setting
            else:
                lo = mid
        return best

    def chosen() -> BlockMerge:
        if size(config) <= target:
            return config
        out = config
        top = max(config.levels, BUDGET_LEVELS)
        for levels in range(config.levels, top + 1):
            loosest = loosened(1.0, levels)
            if size(loosest) <= target:
                lo = max(config.color_range, 1e-3) if levels == config.levels else 1e-3
                return bisect(lo, 1.0, lambda c, n=levels: loosened(c, n))
            out = min(out, loosest, key=size)
        loosest = loosened(1.0, top, BUDGET_GEOMETRY)
        if size(loosest) > target:
            return min(out, loosest, key=size)
        return bisect(1.0, BUDGET_GEOMETRY, lambda f: loosened(1.0, top, f))

    return merge_blocks(g, pixels, depth, intrinsics, chosen(), eps2d=eps2d, with_owners=with_owners, colors=colors)
