"""No more Gaussians than an image needs (`gaussians.parsimony`): flat blocks merged, duplicates
of the other keyframe left to one copy; what renders before renders after."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch

from drivingscene.errors import InputError
from drivingscene.gaussians.assembly import gaussians_from_pixels, pixel_footprints, surfel_frames
from drivingscene.gaussians.parsimony import BlockMerge, KeyframeDedupe, keyframe_duplicates, merge_blocks
from drivingscene.render.project import EPS2D
from drivingscene.render.rasterize import rasterize

H, W = 24, 32
K = torch.tensor([[40.0, 0, 15.5], [0, 40.0, 11.5], [0, 0, 1]])
KS = K.expand(4, 3, 3)


def _assemble(depth: torch.Tensor, colors: torch.Tensor, flows: torch.Tensor | None = None):
    """Per-pixel Gaussians of images ``depth`` ``[I, H, W]`` seen by cameras at the origin (camera
    i of keyframe i // 2 when I > 1), as the model assembles them, and each Gaussian's pixel."""
    num = depth.shape[0]
    k = K.expand(num, 3, 3)
    quats, log_scales = surfel_frames(depth, k, backend="torch")
    log_scales = pixel_footprints(depth, k, quats, log_scales)
    g = gaussians_from_pixels(
        depth, k, torch.eye(4).expand(num, 4, 4), colors, keyframe=torch.arange(num) // 2,
        camera_ids=torch.arange(num) % 2, log_scales=log_scales, quats=quats, flows=flows, footprints=None,
    )  # fmt: skip
    return g, torch.arange(num * H * W)


def _render(g):
    out = rasterize(
        g.means, g.quats, g.scales, g.opacities, g.colors(), torch.eye(4)[None], K[None], W, H, background=torch.zeros(3)
    )
    return out.colors[0], out.alphas[0]


def _psnr(a, b) -> float:
    return float(-10 * torch.log10(((a - b) ** 2).mean()))


def test_a_flat_wall_of_one_colour_is_a_quarter_of_the_gaussians_and_renders_the_same():
    depth = torch.full((1, H, W), 5.0)
    colors = torch.tensor([0.3, 0.5, 0.7]).expand(1, H, W, 3)
    g, pixels = _assemble(depth, colors)
    merged = merge_blocks(g, pixels, depth, KS[: len(depth)], BlockMerge(levels=1), eps2d=EPS2D)
    assert len(merged) == len(g) // 4
    before, alpha_before = _render(g)
    after, alpha_after = _render(merged)
    inner = (slice(2, -2), slice(2, -2))  # the border's splats differ: its last pixel has no neighbour
    assert _psnr(after[inner], before[inner]) > 40
    assert float(alpha_before[inner].min()) > 0.95 and float(alpha_after[inner].min()) > 0.95  # no holes open (issue 45's 0.95)
    # a second level: one Gaussian per 4x4 pixels, still closed
    twice = merge_blocks(g, pixels, depth, KS[: len(depth)], BlockMerge(levels=2), eps2d=EPS2D)
    assert len(twice) == len(g) // 16
    assert _psnr(_render(twice)[0][inner], before[inner]) > 35


def test_texture_depth_edges_motion_and_view_binding_keep_their_pixels():
    depth = torch.full((1, H, W), 5.0)
    checker = ((torch.arange(H)[:, None] + torch.arange(W)[None]) % 2).float()
    colors = (0.3 + 0.2 * checker)[None, :, :, None].expand(1, H, W, 3)
    g, pixels = _assemble(depth, colors)
    assert len(merge_blocks(g, pixels, depth, KS[: len(depth)], eps2d=EPS2D)) == len(g)  # each block holds a 0.2 range of colour
    # a depth edge through every block
    edged = torch.where(torch.arange(W) % 2 == 0, 5.0, 9.0).expand(1, H, W).clone()
    flat = torch.full((1, H, W, 3), 0.5)
    g, pixels = _assemble(edged, flat)
    assert len(merge_blocks(g, pixels, edged, KS[:1], eps2d=EPS2D)) == len(g)
    # one Gaussian of a block moving: nothing that moves is merged with what does not
    flows = torch.zeros(1, H, W, 3)
    flows[0, ::2, ::2, 0] = 0.5
    g, pixels = _assemble(depth, flat, flows)
    assert len(merge_blocks(g, pixels, depth, KS[: len(depth)], eps2d=EPS2D)) == len(g)
    # a block moving as one merges, with its flow
    flows = torch.zeros(1, H, W, 3)
    flows[0, :2, :2, 0] = 0.5
    g, pixels = _assemble(depth, flat, flows)
    merged = merge_blocks(g, pixels, depth, KS[: len(depth)], BlockMerge(levels=1), eps2d=EPS2D)
    assert len(merged) == len(g) // 4 and int(merged.dynamic.sum()) == 1
    torch.testing.assert_close(merged.flows[merged.dynamic], torch.tensor([[0.5, 0.0, 0.0]]))
    # view-bound Gaussians merge with view-bound ones only
    bound = torch.zeros(len(g), 3)
    bound[: W // 2 * 2 : 2, 2] = 1.0  # every other pixel of the first row
    g2 = replace(g, flows=torch.zeros_like(g.flows), view_rays=bound)
    merged = merge_blocks(g2, pixels, depth, KS[:1], BlockMerge(levels=1), eps2d=EPS2D)
    assert len(merged) == len(g) // 4 + 3 * (W // 2)  # the first row's blocks stay per pixel


def test_missing_pixels_and_layers_are_kept_apart_and_in_image_order():
    depth = torch.full((4, H, W), 5.0)
    colors = torch.full((4, H, W, 3), 0.5)
    g, pixels = _assemble(depth, colors)
    hole = torch.ones(len(g), dtype=torch.bool)
    hole[5] = False  # the sky, the ego body or a carved Gaussian: its block keeps its other three
    g, pixels = g.index(hole), pixels[hole]
    merged = merge_blocks(g, pixels, depth, KS[: len(depth)], BlockMerge(levels=1), eps2d=EPS2D)
    assert len(merged) == 4 * (H * W // 4) - 1 + 3
    image = merged.keyframes * 2 + merged.cameras
    assert bool((image[1:] >= image[:-1]).all())  # grouped by keyframe, then camera: the layers' order
    assert torch.equal(torch.bincount(image), torch.tensor([H * W // 4 + 2, H * W // 4, H * W // 4, H * W // 4]))
    with pytest.raises(InputError, match="BlockMerge"):
        BlockMerge(levels=0)


def _plane_pair(shift: float):
    """Depth of a wall 6 m ahead at both keyframes of one camera that moves ``shift`` metres forward,
    the images of a smooth pattern painted on the wall."""
    depth = torch.stack([torch.full((H, W), 6.0), torch.full((H, W), 6.0 - shift)])[:, None]  # [2, 1, H, W]
    u = torch.arange(W, dtype=torch.float32)
    images = []
    for k in (0, 1):
        x = (u - K[0, 2]) / K[0, 0] * depth[k, 0, 0, 0]  # metres along the wall
        pattern = 0.5 + 0.3 * torch.sin(2 * math.pi * x / 3.0)
        images.append(pattern[None, None, :].expand(3, H, W))
    cams = torch.eye(4).repeat(2, 1, 1, 1)
    cams[1, 0, 2, 3] = shift
    return depth, torch.stack(images)[:, None], cams


def test_duplicates_of_the_other_keyframe_are_left_to_one_copy():
    depth, images, cams = _plane_pair(0.5)
    static = torch.ones(2, 1, H, W, dtype=torch.bool)
    dup = keyframe_duplicates(depth, static, images, cams, K[None])
    # keyframe 1 is nearer, so it samples the wall more finely: keyframe 0's copies give way where
    # keyframe 1 sees them, and keyframe 1 keeps all of its own
    assert not dup[1].any()
    assert 0.5 < float(dup[0].float().mean()) < 1.0  # its border, outside keyframe 1's view, stays
    assert not dup[0, 0, 0, 0] and dup[0, 0, H // 2, W // 2]
    # moving pixels, another depth or other colours there: no duplicate
    assert not keyframe_duplicates(depth, torch.zeros_like(static), images, cams, K[None]).any()
    other = depth.clone()
    other[1] = 8.0
    assert not keyframe_duplicates(other, static, images, cams, K[None]).any()
    assert not keyframe_duplicates(depth, static, torch.stack([images[0], 1 - images[1]]), cams, K[None]).any()
    # a camera that did not move: keyframe 0 samples as finely and keyframe 1's copy gives way
    still = keyframe_duplicates(depth[[0, 0]], static, images[[0, 0]], torch.eye(4).repeat(2, 1, 1, 1), K[None])
    assert still[1].all() and not still[0].any()
    loose = keyframe_duplicates(other, static, images, cams, K[None], KeyframeDedupe(depth_tolerance=0.5, color_tolerance=1.0))
    assert loose[0].any()


def test_a_budget_loosens_colour_then_small_depth_steps_but_never_merges_across_depth_edges():
    from drivingscene.gaussians.parsimony import merge_to_budget

    # a wall of a smooth gradient: no block is flat to the default range, all are flat to a wider one
    depth = torch.full((1, H, W), 5.0)
    ramp = torch.linspace(0.2, 0.8, W)[None, None, :, None].expand(1, H, W, 3)
    g, pixels = _assemble(depth, ramp)
    ranged = BlockMerge(color_range=0.01, color_test="range")
    assert len(merge_blocks(g, pixels, depth, KS[:1], ranged, eps2d=EPS2D)) == len(g)
    for share in (0.5, 0.25, 0.1):
        out = merge_to_budget(g, pixels, depth, KS[:1], replace(ranged, budget=share), eps2d=EPS2D)
        assert len(out) <= share * len(g)
    # the budget met already: the configured merge as it is
    flat = torch.full((1, H, W, 3), 0.5)
    g, pixels = _assemble(depth, flat)
    plain = merge_blocks(g, pixels, depth, KS[:1], BlockMerge(), eps2d=EPS2D)
    assert len(merge_to_budget(g, pixels, depth, KS[:1], BlockMerge(budget=0.5), eps2d=EPS2D)) == len(plain)
    # a small depth step (18 % of the depth) through every block: past the default's depth range, so a
    # budget that colour alone cannot meet loosens the depth tests
    stepped = torch.where(torch.arange(W) % 2 == 0, 5.0, 6.0).expand(1, H, W).clone()
    g, pixels = _assemble(stepped, flat)
    assert len(merge_blocks(g, pixels, stepped, KS[:1], BlockMerge(), eps2d=EPS2D)) == len(g)
    assert len(merge_to_budget(g, pixels, stepped, KS[:1], BlockMerge(budget=0.25), eps2d=EPS2D)) <= 0.25 * len(g)
    # a depth edge (57 % of the depth) through every block: no budget merges it, the result is as close as it gets
    edged = torch.where(torch.arange(W) % 2 == 0, 5.0, 9.0).expand(1, H, W).clone()
    g, pixels = _assemble(edged, flat)
    assert len(merge_to_budget(g, pixels, edged, KS[:1], BlockMerge(budget=0.25), eps2d=EPS2D)) == len(g)
    with pytest.raises(InputError, match="budget"):
        BlockMerge(budget=1.5)


def test_the_budget_counts_a_merge_from_its_tests_as_the_merge_itself_comes_out():
    """`merge_to_budget` bisects on `_merged_count` (the tests alone, no Gaussian built): on a scene
    with texture, a gradient, a depth step, sky holes and a moving patch it must equal the length of
    the merge it stands for at every setting tried."""
    from drivingscene.gaussians.parsimony import _first_level, _merged_count

    gen = torch.Generator().manual_seed(3)
    depth = torch.full((2, H, W), 5.0)
    depth[:, :, W // 2 :] = 5.6  # a step of 11 %: merges only with the depth tests loosened
    ramp = torch.linspace(0.2, 0.8, W)[None, None, :, None].expand(2, H, W, 3).clone()
    ramp[:, : H // 3] += 0.05 * torch.rand(2, H // 3, W, 3, generator=gen)  # texture along the top
    flows = torch.zeros(2, H, W, 3)
    flows[:, H // 2 :, : W // 4] = torch.tensor([0.5, 0.0, 0.0])  # a moving patch
    g, pixels = _assemble(depth, ramp, flows)
    keep = torch.rand(len(g), generator=gen) > 0.05  # holes: sky, carved
    g, pixels = g.index(keep), pixels[keep]
    for test in ("detail", "range"):
        for levels in (1, 2, 3):
            for color_range in (0.005, 0.02, 0.1, 1.0):
                for geometry in (1.0, 4.0):
                    config = BlockMerge(
                        color_range=color_range, color_test=test, levels=levels,
                        planarity=0.03 * geometry, depth_range=0.1 * geometry,
                    )  # fmt: skip
                    merged = merge_blocks(g, pixels, depth, KS[:2], config, eps2d=EPS2D)
                    assert _merged_count(_first_level(g, pixels, depth, None, config), config) == len(merged), config


def test_a_smooth_gradient_merges_by_detail_and_texture_does_not():
    """The "detail" test bounds how far a pixel is from its blocks' means interpolated, what the
    merged splats draw: a gradient far wider than ``color_range`` across a block merges, a fine
    texture of a smaller range does not; the "range" test refuses both."""
    depth = torch.full((1, H, W), 5.0)
    ramp = torch.linspace(0.1, 0.9, W)[None, None, :, None].expand(1, H, W, 3)  # 0.05 across a block
    g, pixels = _assemble(depth, ramp)
    detail = BlockMerge(color_range=0.02, color_test="detail", levels=1)
    assert len(merge_blocks(g, pixels, depth, KS[:1], detail, eps2d=EPS2D)) == len(g) // 4
    assert len(merge_blocks(g, pixels, depth, KS[:1], replace(detail, color_test="range"), eps2d=EPS2D)) == len(g)
    checker = ((torch.arange(H)[:, None] + torch.arange(W)[None]) % 2).float()
    g, pixels = _assemble(depth, (0.5 + 0.06 * checker)[None, :, :, None].expand(1, H, W, 3))
    assert len(merge_blocks(g, pixels, depth, KS[:1], detail, eps2d=EPS2D)) == len(g)
    # the colours the test reads can be given: the same texture read as flat merges
    flat = torch.full((len(g), 3), 0.5)
    assert len(merge_blocks(g, pixels, depth, KS[:1], detail, eps2d=EPS2D, colors=flat)) == len(g) // 4
    with pytest.raises(InputError, match="color_test"):
        BlockMerge(color_test="median")


def test_owners_name_the_merged_gaussian_each_pixel_became():
    """``with_owners``: the output Gaussian each input became, at every level: a merged Gaussian is
    the mean of the Gaussians that name it, in its image."""
    depth = torch.full((2, H, W), 5.0)
    depth[1, :, 20:] = 9.0  # a depth edge in the second image
    colors = torch.tensor([0.3, 0.5, 0.7]).expand(2, H, W, 3).clone()
    colors[0, :, :6] = torch.rand(H, 6, 3, generator=torch.Generator().manual_seed(0))  # texture: per pixel
    g, pixels = _assemble(depth, colors)
    keep = torch.rand(len(g), generator=torch.Generator().manual_seed(1)) > 0.02  # a few carved
    g, pixels = g.index(keep), pixels[keep]
    for levels in (1, 2, 3):
        out, owners = merge_blocks(g, pixels, depth, KS[:2], BlockMerge(levels=levels), eps2d=EPS2D, with_owners=True)
        assert torch.equal(out.means, merge_blocks(g, pixels, depth, KS[:2], BlockMerge(levels=levels), eps2d=EPS2D).means)
        counts = torch.bincount(owners, minlength=len(out))
        assert int(counts.min()) == 1 and int(counts.max()) == 4**levels
        mean = torch.zeros(len(out), 3).index_add_(0, owners, g.means) / counts[:, None]
        torch.testing.assert_close(mean, out.means, rtol=0, atol=1e-5)
        assert torch.equal(out.cameras[owners], g.cameras) and torch.equal(out.keyframes[owners], g.keyframes)


def test_the_image_is_sharpened_as_the_solve_would_and_flat_regions_stay_flat():
    from drivingscene.gaussians.parsimony import sharpened

    flat = torch.full((2, 8, 10, 3), 0.4)
    torch.testing.assert_close(sharpened(flat), flat)
    edge = flat.clone()
    edge[:, :, 5:] = 0.8
    out = sharpened(edge)
    assert float(out[0, 4, 4, 0]) < 0.4 and float(out[0, 4, 5, 0]) > 0.8  # an overshoot each side of the edge
    torch.testing.assert_close(out[:, :, [0, 9]], edge[:, :, [0, 9]])  # away from the edge: unchanged
