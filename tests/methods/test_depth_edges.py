import numpy as np
import pytest
import torch

from drivingscene.bench.choices import parse_variant
from drivingscene.methods.depth_edges import EdgeSharpen, sharpen_depth_edges
from drivingscene.methods.feedforward import InferenceOptions


def _two_colours(height: int = 24, width: int = 40, edge: int = 20) -> torch.Tensor:
    image = torch.zeros(3, height, width)
    image[0, :, :edge] = 0.9  # red on the left
    image[2, :, edge:] = 0.9  # blue on the right
    return image


def test_a_ramp_across_a_colour_edge_becomes_a_step_at_the_edge():
    height, width, edge = 24, 40, 20
    x = torch.arange(width, dtype=torch.float32)
    depth = (10 + (x - 15).clamp(0, 10)).expand(height, width).clone()  # 10 m, a ramp over x 15..25, 20 m
    out = sharpen_depth_edges(
        depth[None], _two_colours(height, width, edge)[None], torch.zeros(1, height, width, dtype=torch.bool)
    )[0]
    row = out[height // 2]
    assert (row[:edge] < 12.0).all(), row  # the red side keeps the near depth up to its edge
    assert (row[edge:] > 18.0).all(), row  # the blue side the far one from its first pixel


def test_a_plane_of_one_colour_keeps_its_depth():
    height, width, radius = 30, 40, 4
    y, x = torch.meshgrid(torch.arange(height, dtype=torch.float32), torch.arange(width, dtype=torch.float32), indexing="ij")
    depth = 10 + 0.1 * x + 0.05 * y
    image = torch.full((3, height, width), 0.5)
    out = sharpen_depth_edges(
        depth[None], image[None], torch.zeros(1, height, width, dtype=torch.bool), EdgeSharpen(radius=radius)
    )[0]
    inner = (slice(radius, -radius), slice(radius, -radius))  # whole windows only
    assert torch.allclose(out[inner], depth[inner], atol=0.06), (out - depth)[inner].abs().max()


def test_excluded_pixels_neither_vote_nor_change():
    height, width = 20, 20
    depth = torch.full((1, height, width), 8.0)
    excluded = torch.zeros(1, height, width, dtype=torch.bool)
    excluded[0, 5:15, 5:12] = True  # most of every window around them
    depth[excluded] = 1000.0
    out = sharpen_depth_edges(depth, torch.full((1, 3, height, width), 0.5), excluded)
    assert (out[excluded] == 1000.0).all() and torch.allclose(out[~excluded], torch.tensor(8.0))


def test_shapes_are_checked_and_the_option_is_selectable():
    with pytest.raises(ValueError, match="images"):
        sharpen_depth_edges(torch.ones(2, 8, 8), torch.ones(2, 3, 8, 9), torch.zeros(2, 8, 8, dtype=torch.bool))
    with pytest.raises(ValueError, match="radius"):
        EdgeSharpen(radius=0)
    assert InferenceOptions().edges is None  # lost on validation pairs (docs/magnification.md)
    assert parse_variant("edges=5,esigma=10").options(InferenceOptions()).edges == EdgeSharpen(radius=5, sigma=10.0)
    assert parse_variant("edges=off").options(InferenceOptions(edges=EdgeSharpen())).edges is None
    batched = sharpen_depth_edges(
        torch.full((2, 3, 8, 8), 5.0), torch.rand(2, 3, 3, 8, 8), torch.zeros(2, 3, 8, 8, dtype=torch.bool)
    )
    assert batched.shape == (2, 3, 8, 8) and np.allclose(batched.numpy(), 5.0)
