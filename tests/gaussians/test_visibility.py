"""Free-space carving: exact depth loses nothing, a floater in front of another camera's surface goes."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from drivingscene.data.tensors import pair_to_tensors
from drivingscene.gaussians.core import Gaussians
from drivingscene.gaussians.visibility import CarveConfig, carve, carving_depths
from drivingscene.geometry.se3 import invert_rigid
from drivingscene.methods.oracle import oracle_reconstruction


def _inputs(pair, recon):
    batch = pair_to_tensors(pair)
    cams = (batch.local_to_world[None, None] @ batch.cam_to_local.double()).flatten(0, 1)
    g = recon.gaussians
    depth = torch.from_numpy(recon.depth).flatten(0, 1)
    sky = depth <= 0
    ids = g.keyframes * pair.num_views + g.cameras
    return g, ids, invert_rigid(cams).float(), batch.intrinsics.repeat(2, 1, 1), depth, sky


def test_exact_depth_loses_no_gaussian(synth_pair):
    recon = oracle_reconstruction(synth_pair, refine=0)
    g, ids, w2c, k, depth, sky = _inputs(synth_pair, recon)
    keep = carve(g, ids, w2c, k, depth, sky, None, CarveConfig())
    assert keep.float().mean() > 0.995  # float rounding at a few grazing pixels at most


def test_a_floater_in_front_of_another_cameras_surface_is_dropped(synth_pair):
    recon = oracle_reconstruction(synth_pair, refine=0)
    g, ids, w2c, k, depth, sky = _inputs(synth_pair, recon)
    # a Gaussian half-way along the ray of camera 0's centre pixel (keyframe 0), claimed by camera 1
    h, w = synth_pair.image_size
    cam = torch.linalg.inv(w2c[0].double())
    d = float(depth[0, h // 2, w // 2]) / 2
    ray = torch.tensor([(w // 2 - k[0, 0, 2]) / k[0, 0, 0], (h // 2 - k[0, 1, 2]) / k[0, 1, 1], 1.0], dtype=torch.float64)
    point = (cam[:3, :3] @ (ray * d) + cam[:3, 3]).float()
    floater = Gaussians.create(
        means=point[None],
        quats=torch.tensor([[1.0, 0, 0, 0]]),
        scales=torch.full((1, 3), 0.1),
        opacities=torch.tensor([0.9]),
        sh=torch.ones(1, 3),
        keyframes=0,
        cameras=1,
    )
    both = Gaussians.cat([g, floater])
    keep = carve(both, torch.cat([ids, torch.tensor([1])]), w2c, k, depth, sky, None, CarveConfig())
    assert not keep[-1]


def test_masked_pixels_give_no_vote_and_sky_is_far():
    depth = torch.tensor([[[5.0, 5.0, 0.0], [5.0, 20.0, 0.0]]])
    sky = torch.tensor([[[False, False, True], [False, False, True]]])
    world = torch.tensor([[[True, False, True], [True, True, True]]])
    d = carving_depths(depth, sky, world, window=1)
    assert d[0, 0, 1] > 1e11 and d[0, 0, 2] == pytest.approx(1e6) and d[0, 1, 1] == 20.0
    d3 = carving_depths(depth, sky, world, window=3)
    assert d3[0, 1, 1] == 5.0  # the window minimum


def test_config_is_checked():
    with pytest.raises(ValueError, match="window"):
        CarveConfig(window=2)
    with pytest.raises(ValueError, match="voters"):
        CarveConfig(voters="some")
    assert np.isclose(CarveConfig().margin, 0.1)


def test_compiled_votes_equal_the_torch_path(synth_pair, compiled_kernels):
    from dataclasses import replace as dc_replace

    from drivingscene.gaussians.visibility import see_through_votes

    recon = oracle_reconstruction(synth_pair, refine=0)
    g, ids, w2c, k, depth, sky = _inputs(synth_pair, recon)
    torch.manual_seed(0)
    noisy = depth * (1.5 + 0.3 * torch.rand_like(depth))  # voters that see every surface too far: many votes
    g = dc_replace(g, flows=0.5 * torch.randn_like(g.means) * g.dynamic[:, None])
    depths = carving_depths(noisy, sky, None, 3)
    times = torch.tensor([0.0] * synth_pair.num_views + [1.0] * synth_pair.num_views)
    for voters in ("all", "same_time"):
        config = CarveConfig(voters=voters)
        want = see_through_votes(g, ids, w2c, k, depths, times, config, backend="torch")
        got = see_through_votes(g, ids, w2c, k, depths, times, config, backend="cpp")
        assert (got != want).float().mean() < 1e-4 and want.sum() > 1000
