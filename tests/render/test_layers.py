"""The "layers" blend: each keyframe's Gaussians rendered alone, blended by time and coverage."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from drivingscene.gaussians.core import Gaussians, rgb_to_sh0
from drivingscene.render.scene import LAYER_FLOOR, render_gaussians

HEIGHT, WIDTH = 16, 24
K = torch.tensor([[[20.0, 0.0, (WIDTH - 1) / 2], [0.0, 20.0, (HEIGHT - 1) / 2], [0.0, 0.0, 1.0]]])
EYE = torch.eye(4)[None]


def _wall(z: float, rgb: tuple[float, float, float], keyframe: int, x_range=(-3.0, 3.0)) -> Gaussians:
    """A grid of small opaque Gaussians at depth z, covering the view for x in ``x_range``."""
    xs = torch.arange(x_range[0], x_range[1], 0.2)
    ys = torch.arange(-3.0, 3.0, 0.2)
    grid = torch.stack(torch.meshgrid(xs, ys, indexing="ij"), -1).reshape(-1, 2)
    n = len(grid)
    return Gaussians.create(
        means=torch.cat([grid * z / 5.0, torch.full((n, 1), z)], 1),
        quats=torch.tensor([1.0, 0, 0, 0]).expand(n, 4),
        scales=torch.full((n, 3), 0.3),
        opacities=torch.full((n,), 0.998),
        sh=rgb_to_sh0(torch.tensor(rgb).expand(n, 3)),
        keyframes=torch.full((n,), keyframe),
    )


def test_where_both_layers_see_a_surface_they_cross_fade_in_time():
    g = Gaussians.cat([_wall(5.0, (1.0, 0.0, 0.0), 0), _wall(5.2, (0.0, 0.0, 1.0), 1)])
    for t in (0.0, 0.3, 1.0):
        out = render_gaussians(g, t, EYE, K, HEIGHT, WIDTH, background=torch.zeros(3), blend="layers")
        w0, w1 = 1 - t + LAYER_FLOOR, t + LAYER_FLOOR
        centre = out.colors[0, HEIGHT // 2, WIDTH // 2]
        torch.testing.assert_close(centre, torch.tensor([w0, 0.0, w1]) / (w0 + w1), atol=1e-2, rtol=0)
    # rendered together, the nearer copy wins outright whatever the time
    together = render_gaussians(g, 0.9, EYE, K, HEIGHT, WIDTH, background=torch.zeros(3), blend="all")
    assert together.colors[0, HEIGHT // 2, WIDTH // 2, 0] > 0.99


def test_a_hole_in_one_layer_is_filled_by_the_other():
    left_only = _wall(5.0, (1.0, 0.0, 0.0), 0, x_range=(-3.0, 0.0))  # keyframe 0 saw the left half
    everything = _wall(5.0, (0.0, 1.0, 0.0), 1)
    g = Gaussians.cat([left_only, everything])
    out = render_gaussians(g, 0.0, EYE, K, HEIGHT, WIDTH, background=torch.zeros(3), blend="layers")
    right = out.colors[0, HEIGHT // 2, WIDTH - 3]
    torch.testing.assert_close(right, torch.tensor([0.0, 1.0, 0.0]), atol=2e-3, rtol=0)
    left = out.colors[0, HEIGHT // 2, 2]
    assert left[0] > 0.9 and left[1] < 0.1  # at t = 0 keyframe 0 dominates where it sees


@pytest.mark.parametrize("t", [0.0, 0.5])
def test_with_one_keyframe_layers_is_the_plain_render(t):
    g = _wall(5.0, (0.2, 0.4, 0.6), 0, x_range=(-1.0, 1.0))
    plain = render_gaussians(g, t, EYE, K, HEIGHT, WIDTH, background=torch.tensor([0.1, 0.1, 0.1]))
    layers = render_gaussians(g, t, EYE, K, HEIGHT, WIDTH, background=torch.tensor([0.1, 0.1, 0.1]), blend="layers")
    torch.testing.assert_close(layers.colors, plain.colors, atol=1e-5, rtol=0)


@pytest.mark.parametrize("blend", ["all", "layers"])
def test_input_views_render_each_keyframe_at_its_own_time(synth_pair, blend):
    """`render_input_views` of the oracle (exact depth, both keyframes) reproduces the inputs of
    both keyframes equally well: keyframe 1's cameras are rendered at t = 1 (a pair without
    per-image capture times), not at t = 0."""
    from drivingscene.eval.metrics import psnr
    from drivingscene.methods.oracle import oracle_reconstruction
    from drivingscene.render.scene import render_input_views

    pair = dataclasses.replace(synth_pair, camera_timestamps=None, camera_ego_to_world=None)
    recon = oracle_reconstruction(pair)
    views = render_input_views(recon, pair, blend=blend).flatten(0, 1).permute(0, 3, 1, 2)
    inputs = torch.from_numpy(pair.images).flatten(0, 1).permute(0, 3, 1, 2).float() / 255
    scores = psnr(views, inputs).view(2, -1).mean(1)
    assert scores.min() > 22 and abs(float(scores[0] - scores[1])) < 3
