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
