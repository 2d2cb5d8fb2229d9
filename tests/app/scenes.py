"""Small procedural scenes for the viewer tests (no files, no GL)."""

from __future__ import annotations

import numpy as np
import torch

from drivingscene.gaussians.core import Gaussians
from drivingscene.gaussians.recon import Reconstruction
from tests.factories import make_pair


def random_gaussians(num: int = 300, sh_degree: int = 1, seed: int = 0, dynamic_fraction: float = 0.4) -> Gaussians:
    """Gaussians 3-9 m in front of a camera at the origin looking along +z, both keyframes, some moving."""
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(num, 3, generator=g) * torch.tensor([1.5, 1.2, 1.0]) + torch.tensor([0.0, 0.0, 6.0])
    moving = torch.rand(num, 1, generator=g) < dynamic_fraction
    return Gaussians.create(
        means,
        torch.randn(num, 4, generator=g),
        0.03 + 0.3 * torch.rand(num, 3, generator=g),
        0.05 + 0.9 * torch.rand(num, generator=g),
        0.5 * torch.randn(num, (sh_degree + 1) ** 2, 3, generator=g),
        flows=torch.randn(num, 3, generator=g) * 0.5 * moving,
        keyframes=(torch.rand(num, generator=g) < 0.5).long(),
    )


def street_recon(num_views: int = 3, height: int = 24, width: int = 32, seed: int = 0, flow: float = 2.0) -> Reconstruction:
    """A reconstruction of ``tests.factories.make_pair``'s rig with Gaussians spread around the ego.

    Ground-plane splats plus a few moving blobs; per-camera maps from the pair's ground truth.
    """
    pair = make_pair(num_views, height, width, seed=seed)
    rng = np.random.default_rng(seed)
    n = 600
    xy = rng.uniform([-5, -12], [30, 6], (n, 2))
    z = np.where(rng.uniform(size=n) < 0.7, 0.0, rng.uniform(0.2, 3.0, n))
    means = torch.from_numpy(np.stack([xy[:, 0], xy[:, 1], z], 1).astype(np.float32))
    moving = torch.from_numpy(rng.uniform(size=(n, 1)) < 0.15)
    g = Gaussians.create(
        means,
        torch.from_numpy(rng.normal(size=(n, 4)).astype(np.float32)),
        torch.from_numpy(rng.uniform(0.1, 0.6, (n, 3)).astype(np.float32)),
        torch.from_numpy(rng.uniform(0.3, 0.95, n).astype(np.float32)),
        torch.from_numpy(rng.normal(scale=0.6, size=(n, 3)).astype(np.float32)),
        flows=torch.tensor([flow, 0.25 * flow, 0.0]) * moving,
        keyframes=torch.from_numpy(rng.integers(0, 2, n)),
        cameras=torch.from_numpy(rng.integers(0, num_views, n)),
    )
    rigid = pair.gt_flow * 0.5
    return Reconstruction.from_pair(
        pair,
        g,
        sky_sh=torch.tensor([[0.9, 1.2, 1.6], [0.0, 0.0, 0.0], [0.3, 0.3, 0.4], [0.0, 0.0, 0.0]]),
        depth=pair.gt_depth,
        rigid_flow=rigid,
        residual_flow=pair.gt_flow - rigid,
        meta={"method": "test"},
    )
