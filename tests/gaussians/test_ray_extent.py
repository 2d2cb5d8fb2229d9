"""Gaussians extended along their view rays (`gaussians.assembly.extend_along_rays`): the step to
the neighbouring pixels on a slope, invisible in the own view, closing the stripes a grazing
surface leaves when seen from elsewhere."""

from __future__ import annotations

import math

import pytest
import torch

from drivingscene.gaussians.assembly import (
    RAY_STEP_CAP,
    extend_along_rays,
    extend_along_rays_torch,
    gaussians_from_pixels,
    slope_steps,
    surfel_frames,
)
from drivingscene.geometry.camera import unproject
from drivingscene.geometry.se3 import quat_to_matrix
from drivingscene.render.project import covariances_3d, project_covariances

K = torch.tensor([[60.0, 0, 23.5], [0, 60.0, 15.5], [0, 0, 1]], dtype=torch.float64)


def _road_depth(height: int = 32, width: int = 48) -> torch.Tensor:
    """``[1, H, W]`` z-depth of a road 1.5 m below a camera at the origin looking along it
    (OpenCV axes: y down), grazing towards the top rows; rows above the horizon at 80 m."""
    v = torch.arange(height, dtype=torch.float64)[:, None].expand(height, width)
    below = (v - K[1, 2]) / K[1, 1]
    return torch.where(below > 0.02, 1.5 / below.clamp(min=0.02), torch.full_like(below, 80.0))[None]


def _cov(quats: torch.Tensor, log_scales: torch.Tensor) -> torch.Tensor:
    r = quat_to_matrix(torch.nn.functional.normalize(quats.double(), dim=-1))
    return r @ torch.diag_embed(torch.exp(2 * log_scales.double())) @ r.transpose(-1, -2)


def test_slope_steps_follow_a_slope_and_skip_peaks_and_valleys():
    depth = _road_depth()
    steps = slope_steps(depth)
    # on the road (monotonic down the rows) the smaller of the two row steps; columns are flat
    rows = 1.5 / ((torch.arange(32, dtype=torch.float64) - K[1, 2]) / K[1, 1])
    r = 24
    expected = min(abs(rows[r + 1] - rows[r]), abs(rows[r] - rows[r - 1]))
    torch.testing.assert_close(steps[0, r], torch.full((48,), float(expected), dtype=torch.float64))
    # a single pixel nearer than every neighbour (a pole, a flying pixel) has no slope through it
    peak = depth.clone()
    peak[0, 24, 20] = 2.0
    assert slope_steps(peak)[0, 24, 20] == 0
    # a flat, fronto-parallel wall has none either
    assert (slope_steps(torch.full((1, 8, 8), 5.0)) == 0).all()


def test_the_extension_is_along_the_ray_and_invisible_in_the_own_view():
    depth = _road_depth()
    quats, log_scales = surfel_frames(depth, K[None], backend="torch")
    q2, s2 = extend_along_rays(depth, K[None], quats, log_scales, 0.7, backend="torch")
    points = unproject(depth, K[None]).reshape(-1, 3)
    before, after = _cov(quats.reshape(-1, 4), log_scales.reshape(-1, 3)), _cov(q2.reshape(-1, 4), s2.reshape(-1, 3))
    ray = torch.nn.functional.normalize(points, dim=-1)
    steps = torch.minimum(slope_steps(depth), RAY_STEP_CAP * depth)  # far steps capped
    sigma = 0.7 * steps.reshape(-1) * points.norm(dim=-1) / points[:, 2]
    expected = before + sigma[:, None, None] ** 2 * ray[:, :, None] * ray[:, None, :]
    torch.testing.assert_close(after, expected, rtol=1e-6, atol=1e-12)
    # the road's rows are extended (but the last, whose step behind is the border's 0), the sky's are not
    assert (sigma.view(32, 48)[18:31] > 0).all() and (sigma.view(32, 48)[:16] == 0).all()
    assert (steps < slope_steps(depth)).any() and (steps <= RAY_STEP_CAP * depth).all()

    def own_view(q, s):
        proj = project_covariances(
            points, covariances_3d(q.reshape(-1, 4), torch.exp(s.reshape(-1, 3))), torch.eye(4, dtype=torch.float64), K, 48, 32,
            eps2d=0.0,
        )  # fmt: skip
        return proj.conics

    torch.testing.assert_close(own_view(q2, s2), own_view(quats, log_scales), rtol=1e-5, atol=1e-8)


def test_seen_from_above_the_extended_road_has_no_stripes():
    """The road's splat rows seen from 6 m above, looking down 45 degrees: without the extension
    the far rows (their stretch capped in the surfel) leave stripes of background between them."""
    from drivingscene.gaussians.assembly import pixel_footprints
    from drivingscene.render.rasterize import rasterize

    depth = _road_depth()
    eye = torch.eye(4, dtype=torch.float64)[None]
    colors = torch.full((1, 32, 48, 3), 0.5, dtype=torch.float64)
    quats, log_scales = surfel_frames(depth, K[None], backend="torch")
    log_scales = pixel_footprints(depth, K[None], quats, log_scales)
    q2, s2 = extend_along_rays(depth, K[None], quats, log_scales, backend="torch")
    road = (depth < 30).reshape(-1)  # below the horizon, within 30 m
    plain = gaussians_from_pixels(depth, K[None], eye, colors, keyframe=0, quats=quats, log_scales=log_scales, footprints=None)
    extended = gaussians_from_pixels(depth, K[None], eye, colors, keyframe=0, quats=q2, log_scales=s2, footprints=None)
    # the viewer: 6 m up (-y), 6 m ahead, its axis down 45 degrees (OpenCV: x right, y down, z ahead)
    c, s = math.cos(math.radians(45.0)), math.sin(math.radians(45.0))
    cam_to_world = torch.eye(4, dtype=torch.float64)
    cam_to_world[:3, :3] = torch.tensor([[1.0, 0, 0], [0, c, s], [0, -s, c]], dtype=torch.float64)
    cam_to_world[:3, 3] = torch.tensor([0.0, -6.0, 6.0], dtype=torch.float64)
    k_top = torch.tensor([[60.0, 0, 63.5], [0, 60.0, 47.5], [0, 0, 1]], dtype=torch.float64)
    # where the road the source camera saw lies in the view: each ray meets the road plane y = 1.5
    v, u = torch.meshgrid(torch.arange(96.0, dtype=torch.float64), torch.arange(128.0, dtype=torch.float64), indexing="ij")
    rays = torch.stack([(u - 63.5) / 60.0, (v - 47.5) / 60.0, torch.ones_like(u)], -1) @ cam_to_world[:3, :3].T
    hit = cam_to_world[:3, 3] + ((1.5 + 6.0) / rays[..., 1])[..., None] * rays
    seen = (rays[..., 1] > 0) & (hit[..., 2] > 8.0) & (hit[..., 2] < 25.0) & (hit[..., 0].abs() < 0.8 * 23.5 / 60.0 * hit[..., 2])

    def open_share(g) -> float:
        g = g.index(road)
        out = rasterize(g.means.float(), g.quats.float(), g.scales.float(), g.opacities.float(), g.colors().float(),
                        torch.linalg.inv(cam_to_world).float()[None], k_top.float()[None], 128, 96)  # fmt: skip
        return float((out.alphas[0][seen] < 0.5).float().mean())

    assert seen.sum() > 1000
    before, after = open_share(plain), open_share(extended)
    assert before > 0.3 and after < 0.05, (before, after)


@pytest.mark.usefixtures("compiled_kernels")
def test_compiled_extension_matches_the_torch_path():
    from drivingscene import kernels

    g = torch.Generator().manual_seed(3)
    n = 4000
    points = torch.randn(n, 3, generator=g)
    points[:, 2] = points[:, 2].abs() + 0.5
    quats = torch.randn(n, 4, generator=g)
    log_scales = torch.randn(n, 3, generator=g) - 3.0
    log_scales[:100, 1] = log_scales[:100, 0]  # two equal axes: a degenerate pair
    log_scales[100:150] = log_scales[100:150, :1]  # isotropic: the ray's axis the only distinct one
    quats[150:200] = torch.tensor([1.0, 0.0, 0.0, 0.0])  # axis-aligned, the ray along z
    points[150:200, :2] = 0.0
    sigma = torch.rand(n, generator=g) * 0.2
    sigma[::7] = 0.0  # unchanged ones
    sigma[1:200:7] = 1e-7  # far below the scales: barely changed
    q_cpp, s_cpp = kernels.extend_along_rays(points, quats, log_scales, sigma)
    q_ref, s_ref = extend_along_rays_torch(points, quats, log_scales, sigma)
    c_cpp, c_ref = _cov(q_cpp, s_cpp), _cov(q_ref, s_ref)
    rel = (c_cpp - c_ref).abs().amax((-1, -2)) / c_ref.abs().amax((-1, -2))
    assert rel.max() < 1e-5
    assert torch.equal(q_cpp[::7], quats[::7]) and torch.equal(s_cpp[::7], log_scales[::7])
    torch.testing.assert_close(q_cpp[sigma > 0].norm(dim=-1), torch.ones(int((sigma > 0).sum())), atol=1e-5, rtol=0)
