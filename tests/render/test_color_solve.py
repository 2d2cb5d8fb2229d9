"""The colour solve (render.color_solve): with geometry fixed, colours that make each image's own
layer re-render it, for the rule that layer is drawn with (surface averaged or composited)."""

from __future__ import annotations

import pytest
import torch

from drivingscene.gaussians.assembly import DEFAULT_OPACITY
from drivingscene.methods.oracle import surfel_maps
from drivingscene.render.color_solve import own_view_splats, solve_pixel_colors
from drivingscene.render.composite import composite, find_pairs_torch, pair_inputs


def _slanted_scene(height: int = 24, width: int = 40):
    """One image of a road-like plane (depth growing up the image) under a random texture."""
    rows = torch.arange(height, dtype=torch.float32)[:, None].expand(height, width)
    depth = (4.0 + 0.15 * (height - rows))[None]  # [1, H, W]: 4.15 m at the bottom to 7.6 m at the top
    k = torch.tensor([[[30.0, 0.0, (width - 1) / 2], [0.0, 30.0, (height - 1) / 2], [0.0, 0.0, 1.0]]])
    # texture at the scale of a few pixels (white noise would need colours far outside [0, 1.5])
    coarse = torch.rand(1, 3, height // 2, width // 2, generator=torch.Generator().manual_seed(0))
    image = 0.2 + 0.6 * torch.nn.functional.interpolate(coarse, size=(height, width), mode="bilinear", align_corners=False)
    return depth, k, image.permute(0, 2, 3, 1).contiguous()


def _own_layer(depth, k, colors, tolerance: float) -> torch.Tensor:
    """``C / alpha`` of the image's own layer at its pixel centres ``[1, H, W, 3]``."""
    quats, log_scales = surfel_maps(depth, k)
    valid = torch.ones_like(depth, dtype=torch.bool)
    opacities = torch.full_like(depth, DEFAULT_OPACITY)
    splats, pixel = own_view_splats(depth, k, quats, log_scales, opacities, valid)
    height, width = depth.shape[1:]
    inp = pair_inputs(splats, width, height)
    ids = find_pairs_torch(inp, width, height, 32)
    rgb, _, alpha = composite(
        ids, inp.means2d, inp.conics, inp.opacities, splats.depths, colors.reshape(-1, 3)[pixel], torch.zeros(1, 3),
        width, height, surface_tolerance=tolerance,
    )  # fmt: skip
    return rgb / alpha[..., None].clamp(min=1e-6)


def _rmse(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a - b).square().mean().sqrt())


def test_the_solve_re_renders_the_image_for_the_rule_it_was_told():
    depth, k, image = _slanted_scene()
    quats, log_scales = surfel_maps(depth, k)
    valid = torch.ones_like(depth, dtype=torch.bool)
    opacities = torch.full_like(depth, DEFAULT_OPACITY)
    plain_colors = _own_layer(depth, k, image, 0.1)  # the image's colours splatted as they are: blurred
    errors = {}
    for solved_for in (0.0, 0.1):
        colors = solve_pixel_colors(
            depth, k, quats, log_scales, opacities, image, image, valid, iterations=4, surface_tolerance=solved_for
        )
        for drawn_with in (0.0, 0.1):
            errors[solved_for, drawn_with] = _rmse(_own_layer(depth, k, colors, drawn_with), image)
    before = _rmse(plain_colors, image)
    assert errors[0.1, 0.1] < 0.3 * before  # the deconvolution of the averaged splats
    assert errors[0.0, 0.0] < 0.6 * before
    # solved for one rule and drawn with the other: worse than the matching pair, each way
    assert errors[0.1, 0.1] < 0.7 * errors[0.1, 0.0]
    assert errors[0.0, 0.0] < 0.7 * errors[0.0, 0.1]
    # the averaged layer is the easier one to invert (no depth order inside the surface)
    assert errors[0.1, 0.1] < errors[0.0, 0.0]


def test_the_solve_leaves_pixels_without_a_gaussian_alone():
    depth, k, image = _slanted_scene(12, 20)
    quats, log_scales = surfel_maps(depth, k)
    valid = torch.ones_like(depth, dtype=torch.bool)
    valid[:, :4] = False  # the top rows are sky
    start = torch.full_like(image, 0.25)
    out = solve_pixel_colors(depth, k, quats, log_scales, torch.full_like(depth, DEFAULT_OPACITY), start, image, valid, 2)
    torch.testing.assert_close(out[:, :4], start[:, :4], rtol=0, atol=0)
    assert float((out[:, 6:] - start[:, 6:]).abs().mean()) > 0.05


@pytest.mark.parametrize("tolerance", [0.0, 0.2])
def test_the_compiled_solve_equals_the_compositing_reference(compiled_kernels, tolerance):
    """The compiled solve (pairs and weights formed once, sparse products) against the torch path's
    compositing pass per step: the same colours, on a scene with a depth edge and sky pixels."""
    depth, k, image = _slanted_scene(30, 44)
    depth[:, 10:20, 12:26] = 2.5  # an object in front of the road: pixels whose lists cross a depth edge
    quats, log_scales = surfel_maps(depth, k)
    valid = torch.ones_like(depth, dtype=torch.bool)
    valid[:, :3] = False  # sky
    opacities = torch.rand(depth.shape, generator=torch.Generator().manual_seed(1)) * 0.5 + 0.45
    start = torch.full_like(image, 0.3)
    start[:, :3] = 7.0  # no Gaussian there: kept as it is, not clamped
    for iterations in (1, 3):
        got, expected = (
            solve_pixel_colors(
                depth,
                k,
                quats,
                log_scales,
                opacities,
                start,
                image,
                valid,
                iterations,
                backend=backend,
                surface_tolerance=tolerance,
            )
            for backend in ("cpp", "torch")
        )
        torch.testing.assert_close(got, expected, rtol=0, atol=2e-5)
        assert torch.equal(got[:, :3], start[:, :3]) and float((got[:, 5:] - start[:, 5:]).abs().mean()) > 0.05


def _merged_scene(height: int = 24, width: int = 40):
    """The slanted road of `_slanted_scene` as per-pixel Gaussians (two images: both keyframes of one
    camera at the origin), smooth colour on its left half and texture on its right, merged by
    `merge_blocks` (the smooth half merges): the merged Gaussians, each input's owner and pixel."""
    from drivingscene.gaussians.assembly import gaussians_from_pixels, pixel_footprints, surfel_frames
    from drivingscene.gaussians.parsimony import BlockMerge, merge_blocks
    from drivingscene.render.project import EPS2D

    depth, k, image = _slanted_scene(height, width)
    noise = torch.rand(1, height, width // 2, 3, generator=torch.Generator().manual_seed(3))
    image[:, :, width // 2 :] = 0.2 + 0.6 * noise  # texture: stays per pixel
    u = torch.linspace(0.0, 1.0, width // 2)
    image[:, :, : width // 2] = torch.stack([0.3 + 0.3 * u, 0.5 - 0.2 * u, 0.4 + 0.1 * u], -1)  # a smooth gradient: merges
    depth, image, k = depth.expand(2, -1, -1), image.expand(2, -1, -1, -1).contiguous(), k.expand(2, 3, 3)
    quats, log_scales = surfel_frames(depth, k, backend="torch")
    log_scales = pixel_footprints(depth, k, quats, log_scales)
    g = gaussians_from_pixels(
        depth, k, torch.eye(4).expand(2, 4, 4), image, keyframe=torch.arange(2), camera_ids=torch.zeros(2, dtype=torch.long),
        log_scales=log_scales, quats=quats, footprints=None,
    )  # fmt: skip
    pixels = torch.arange(2 * height * width)
    merged, owners = merge_blocks(g, pixels, depth, k, BlockMerge(levels=2), eps2d=EPS2D, with_owners=True)
    return merged, owners, pixels, image, k


def _own_layers(g, k, height, width, tolerance):
    """Each image's own layer, ``C / alpha`` ``[I, H, W, 3]``, through the general rasterizer."""
    from drivingscene.render.rasterize import rasterize

    views = g.keyframes.long() + g.cameras.long()  # one camera per keyframe
    out = rasterize(
        g.means, g.quats, g.scales, g.opacities, g.colors(), torch.eye(4).expand(len(k), 4, 4), k, width, height,
        views=views, surface_tolerance=tolerance, backend="torch",
    )  # fmt: skip
    return out.colors / out.alphas[..., None].clamp(min=1e-6)


def test_merged_gaussians_solved_over_their_pixels_re_render_the_image_better_than_their_means():
    from drivingscene.render.color_solve import solve_gaussian_colors

    height, width = 24, 40
    merged, owners, pixels, image, k = _merged_scene(height, width)
    assert len(merged) < 0.7 * len(pixels)  # the smooth half merged, at two levels
    counts = torch.bincount(owners, minlength=len(merged))
    assert int(counts.max()) == 16 and int(counts.min()) == 1
    solved = solve_gaussian_colors(merged, owners, pixels, image, torch.eye(4).expand(2, 4, 4), k, 4, backend="torch")
    before, after = (_own_layers(x, k, height, width, 0.2) for x in (merged, solved))
    smooth = (slice(None), slice(2, -2), slice(2, width // 2 - 2))  # the merged gradient, away from the borders
    assert _rmse(after[smooth], image[smooth]) < 0.5 * _rmse(before[smooth], image[smooth])
    assert _rmse(after, image) < 0.8 * _rmse(before, image)  # the texture too (white noise: the hardest to re-render)
    # what moves is the DC colour only, and the geometry not at all
    assert torch.equal(solved.means, merged.means) and torch.equal(solved.log_scales, merged.log_scales)


def test_the_compiled_solve_over_merged_gaussians_equals_the_compositing_reference(compiled_kernels):
    from drivingscene.render.color_solve import solve_gaussian_colors

    merged, owners, pixels, image, k = _merged_scene(30, 44)
    eye = torch.eye(4).expand(2, 4, 4)
    for iterations in (1, 3):
        got, expected = (
            solve_gaussian_colors(merged, owners, pixels, image, eye, k, iterations, backend=backend)
            for backend in ("cpp", "torch")
        )
        torch.testing.assert_close(got.sh, expected.sh, rtol=0, atol=1e-4)
        assert float((got.sh - merged.sh).abs().mean()) > 0.01


def test_per_pixel_gaussians_solved_as_their_own_owners_match_the_map_solve():
    """A Gaussian that stands for its own pixel alone is the per-pixel solve: projected splats and
    splats built from the maps give the same colours."""
    from drivingscene.gaussians.assembly import gaussians_from_pixels
    from drivingscene.render.color_solve import solve_gaussian_colors

    depth, k, image = _slanted_scene()
    quats, log_scales = surfel_maps(depth, k)
    valid = torch.ones_like(depth, dtype=torch.bool)
    opacities = torch.full_like(depth, DEFAULT_OPACITY)
    start = torch.full_like(image, 0.4)
    maps = solve_pixel_colors(depth, k, quats, log_scales, opacities, start, image, valid, 3, backend="torch")
    g = gaussians_from_pixels(
        depth, k, torch.eye(4)[None], start, keyframe=torch.zeros(1, dtype=torch.long), camera_ids=torch.zeros(1, dtype=torch.long),
        log_scales=log_scales, quats=quats, footprints=None,
    )  # fmt: skip
    pixels = torch.arange(depth.numel())
    solved = solve_gaussian_colors(g, pixels, pixels, image, torch.eye(4)[None], k, 3, backend="torch")
    torch.testing.assert_close(solved.colors(), maps.reshape(-1, 3), rtol=0, atol=2e-3)


def test_the_general_solve_names_what_it_expected():
    from drivingscene.errors import InputError
    from drivingscene.render.color_solve import solve_gaussian_colors

    merged, owners, pixels, image, k = _merged_scene(12, 20)
    with pytest.raises(InputError, match="owners and pixels"):
        solve_gaussian_colors(merged, owners[:-1], pixels, image, torch.eye(4).expand(2, 4, 4), k)


def test_own_view_splats_of_assembled_gaussians_are_what_the_renderer_projects():
    """Gaussians that stand on their own image's pixels (rotated, moved cameras with skew; views out of
    order; some behind the camera or too faint to draw): the splats built image by image equal
    ``make_splats(..., views=...)``, pair for pair and in compositing order."""
    from drivingscene.gaussians.core import Gaussians
    from drivingscene.render.color_solve import own_view_splats_of
    from drivingscene.render.project import EPS2D
    from drivingscene.render.splats import make_splats

    gen = torch.Generator().manual_seed(3)
    num, n, width, height = 3, 400, 48, 32
    angles = torch.tensor([0.3, -1.1, 2.0])
    rot = torch.zeros(num, 3, 3)
    rot[:, 0, 0], rot[:, 0, 2], rot[:, 1, 1], rot[:, 2, 0], rot[:, 2, 2] = (
        angles.cos(),
        angles.sin(),
        1.0,
        -angles.sin(),
        angles.cos(),
    )
    world_to_cam = torch.eye(4).repeat(num, 1, 1)
    world_to_cam[:, :3, :3] = rot
    world_to_cam[:, :3, 3] = torch.randn(num, 3, generator=gen)
    k = torch.tensor([[40.0, 0.5, 23.5], [0.0, 38.0, 15.5], [0.0, 0.0, 1.0]]).repeat(num, 1, 1)
    k[1, 0, 0] = 55.0
    views = torch.randint(0, num, (n,), generator=gen)
    uv = torch.rand(n, 2, generator=gen) * torch.tensor([width - 1.0, height - 1.0])
    z = 2.0 + 20.0 * torch.rand(n, generator=gen)
    z[:5] = -1.0  # behind its camera: never drawn
    kv = k[views]
    y = (uv[:, 1] - kv[:, 1, 2]) / kv[:, 1, 1]
    x = (uv[:, 0] - kv[:, 0, 2] - kv[:, 0, 1] * y) / kv[:, 0, 0]
    p_cam = torch.stack([x * z, y * z, z], -1)
    rv, tv = world_to_cam[views, :3, :3], world_to_cam[views, :3, 3]
    means = ((p_cam - tv)[:, None, :] @ rv)[:, 0]  # R^T (p - t)
    opacity = 0.05 + 0.9 * torch.rand(n, generator=gen)
    opacity[5:9] = 1e-3  # fainter than the renderer draws
    g = Gaussians(
        means=means, quats=torch.nn.functional.normalize(torch.randn(n, 4, generator=gen), dim=-1),
        log_scales=torch.log(0.02 + 0.1 * torch.rand(n, 3, generator=gen)) + torch.log(z.abs())[:, None] - 3.0,
        opacity_logits=torch.logit(opacity), sh=torch.zeros(n, 1, 3), flows=torch.zeros(n, 3),
        keyframes=torch.zeros(n, dtype=torch.long), cameras=views, view_rays=torch.zeros(n, 3),
    )  # fmt: skip
    got = own_view_splats_of(g, views, world_to_cam, k, width, height, EPS2D)
    expected = make_splats(
        g.means, g.quats, g.scales, g.opacities, torch.zeros(n, 3), world_to_cam, k, width, height,
        sh_degree=None, near=0.01, far=1e10, eps2d=EPS2D, views=views,
    )  # fmt: skip
    assert len(got.gaussian_ids) == n - 9
    assert torch.equal(got.gaussian_ids, expected.gaussian_ids) and torch.equal(got.camera_ids, expected.camera_ids)
    assert torch.equal(got.camera_offsets, expected.camera_offsets)
    for name in ("means2d", "conics", "depths", "radii", "opacities"):
        torch.testing.assert_close(getattr(got, name), getattr(expected, name), rtol=1e-4, atol=1e-4)
