"""Fixtures for the rasterizer tests: small random scenes and the compiled pair-finding step (built once)."""

from __future__ import annotations

import math

import pytest
import torch


def random_scene(num: int = 40, num_cams: int = 2, width: int = 32, height: int = 24, seed: int = 0, sh_degree=None):
    """Random Gaussians 3-7 m in front of ``num_cams`` nearby cameras, as ``rasterize`` keyword arguments."""
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(num, 3, generator=g) * torch.tensor([1.2, 0.9, 1.0]) + torch.tensor([0.0, 0.0, 5.0])
    colors = (
        torch.rand(num, 3, generator=g) if sh_degree is None else 0.4 * torch.randn(num, (sh_degree + 1) ** 2, 3, generator=g)
    )
    viewmats = torch.eye(4).repeat(num_cams, 1, 1)
    for b in range(1, num_cams):
        yaw = 0.1 * b
        viewmats[b, :3, :3] = torch.tensor([[math.cos(yaw), 0, -math.sin(yaw)], [0, 1, 0], [math.sin(yaw), 0, math.cos(yaw)]])
        viewmats[b, :3, 3] = torch.tensor([0.3 * b, -0.1 * b, 0.2 * b])
    f = 0.9 * width
    Ks = torch.tensor([[f, 0.0, (width - 1) / 2], [0.0, f, (height - 1) / 2], [0.0, 0.0, 1.0]]).repeat(num_cams, 1, 1)
    return dict(
        means=means,
        quats=torch.randn(num, 4, generator=g),
        scales=0.03 + 0.25 * torch.rand(num, 3, generator=g),
        opacities=0.05 + 0.9 * torch.rand(num, generator=g),
        colors=colors,
        viewmats=viewmats,
        Ks=Ks,
        width=width,
        height=height,
        sh_degree=sh_degree,
    )


@pytest.fixture(scope="session")
def cpp_op(compiled_kernels):
    """The compiled find_pairs wrapper (the kernels are built once per session; skipped without a compiler)."""
    return compiled_kernels.find_pairs


@pytest.fixture
def backend(kernel_backend):
    """Both rasterizer paths, "torch" and "cpp" (`kernel_backend`)."""
    return kernel_backend


def max_contributors(scene: dict) -> int:
    """Most Gaussians contributing to one pixel (no layer cap), from the torch pair finder."""
    from drivingscene.render.composite import find_pairs_torch, pair_inputs
    from drivingscene.render.splats import make_splats

    kw = {k: scene[k] for k in ("means", "quats", "scales", "opacities", "colors", "viewmats", "Ks", "width", "height")}
    s = make_splats(**kw, sh_degree=scene.get("sh_degree"), near=0.01, far=1e10, eps2d=0.3)
    ids = find_pairs_torch(pair_inputs(s, scene["width"], scene["height"]), scene["width"], scene["height"], 1024)
    return int((ids >= 0).sum(1).max())
