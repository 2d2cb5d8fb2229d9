"""Gaussians container, time evaluation, assembly from depth and the recon.npz round trip."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from drivingscene.data.npz import save_npz
from drivingscene.errors import InputError, SceneFormatError
from drivingscene.gaussians import Gaussians, Reconstruction, gaussians_from_pixels, load_reconstruction, save_reconstruction
from drivingscene.gaussians.assembly import FOOTPRINT
from drivingscene.gaussians.recon import recon_to_arrays, validate_recon_arrays
from drivingscene.geometry import quat_to_matrix, unproject
from drivingscene.geometry.flow import cams_to_world
from tests.factories import make_pair


def random_gaussians(n: int = 50, degree: int = 0, seed: int = 0, dynamic_share: float = 0.3) -> Gaussians:
    g = torch.Generator().manual_seed(seed)
    flows = torch.randn(n, 3, generator=g)
    flows[torch.rand(n, generator=g) > dynamic_share] = 0
    return Gaussians.create(
        means=torch.randn(n, 3, generator=g) * 5,
        quats=torch.randn(n, 4, generator=g),
        scales=torch.rand(n, 3, generator=g) * 0.2 + 0.01,
        opacities=torch.rand(n, generator=g) * 0.9 + 0.05,
        sh=torch.randn(n, (degree + 1) ** 2, 3, generator=g) * 0.3,
        flows=flows,
        keyframes=(torch.rand(n, generator=g) > 0.5).long(),
        cameras=torch.randint(0, 6, (n,), generator=g),
    )


def test_means_at_time_moves_each_keyframe_towards_the_other():
    g = Gaussians.create(
        means=torch.tensor([[0.0, 0, 0], [10.0, 0, 0]]),
        quats=torch.tensor([[1.0, 0, 0, 0]] * 2),
        scales=torch.ones(2, 3),
        opacities=torch.ones(2) * 0.5,
        sh=torch.zeros(2, 3),
        flows=torch.tensor([[10.0, 0, 0], [-10.0, 0, 0]]),
        keyframes=torch.tensor([0, 1]),
    )
    torch.testing.assert_close(g.means_at(0.0), torch.tensor([[0.0, 0, 0], [0.0, 0, 0]]))
    torch.testing.assert_close(g.means_at(1.0), torch.tensor([[10.0, 0, 0], [10.0, 0, 0]]))
    torch.testing.assert_close(g.means_at(0.25), torch.tensor([[2.5, 0, 0], [2.5, 0, 0]]))
    moved = g.at_time(0.25)
    assert not moved.dynamic.any() and (moved.keyframes == 0).all()


def test_shape_errors_name_the_field():
    with pytest.raises(InputError, match=r"Gaussians.log_scales: expected shape \[3, 3\], found \[3, 2\]"):
        Gaussians.create(torch.zeros(3, 3), torch.ones(3, 4), torch.ones(3, 2), torch.ones(3), torch.zeros(3, 3))
    with pytest.raises(InputError, match="degree 0-3"):
        Gaussians.create(torch.zeros(3, 3), torch.ones(3, 4), torch.ones(3, 3), torch.ones(3), torch.zeros(3, 5, 3))


def test_cat_pads_sh_and_index_selects():
    a, b = random_gaussians(10, degree=0), random_gaussians(5, degree=2, seed=1)
    both = Gaussians.cat([a, b])
    assert len(both) == 15 and both.sh_degree == 2
    torch.testing.assert_close(both.sh[:10, 0], a.sh[:, 0])
    assert both.sh[:10, 1:].abs().max() == 0
    sub = both.index(both.keyframes == 1)
    assert len(sub) == int((both.keyframes == 1).sum())


def test_assembly_places_gaussians_on_the_surface():
    pair = make_pair(num_views=2, height=6, width=8)
    depth = torch.full((2, 6, 8), 7.0)  # fronto-parallel planes: surfels face the camera
    k = torch.from_numpy(pair.intrinsics)
    c2w = cams_to_world(torch.from_numpy(pair.cam_to_ego), torch.from_numpy(pair.ego_to_world[0]).float())
    depth[0, 0, 0] = 0  # sky: no Gaussian
    rgb = torch.from_numpy(pair.images[0]).float() / 255
    g = gaussians_from_pixels(depth, k, c2w, rgb, keyframe=0)
    assert len(g) == 2 * 6 * 8 - 1
    # Independent check of one Gaussian: camera 1, pixel (row 2, col 3).
    p_cam = torch.linalg.inv(k[1]) @ torch.tensor([3.0, 2.0, 1.0]) * depth[1, 2, 3]
    expected = c2w[1, :3, :3] @ p_cam + c2w[1, :3, 3]
    idx = 6 * 8 - 1 + 2 * 8 + 3
    torch.testing.assert_close(g.means[idx], expected, atol=1e-4, rtol=1e-5)
    torch.testing.assert_close(g.colors()[idx], rgb[1, 2, 3], atol=1e-6, rtol=0)
    # The surfel normal (third axis, the thin one) is the camera's viewing axis.
    normal = quat_to_matrix(g.quats[idx])[:, 2]
    torch.testing.assert_close((normal @ c2w[1, :3, 2]).abs(), torch.tensor(1.0), atol=1e-5, rtol=0)
    assert g.scales[idx, 2] < g.scales[idx, 0]
    assert (g.cameras[: 6 * 8 - 1] == 0).all() and (g.cameras[6 * 8 - 1 :] == 1).all()


def test_assembly_is_differentiable():
    pair = make_pair(num_views=1, height=4, width=5)
    depth = torch.from_numpy(pair.gt_depth[0]).requires_grad_()
    c2w = cams_to_world(torch.from_numpy(pair.cam_to_ego), torch.eye(4))
    g = gaussians_from_pixels(depth, torch.from_numpy(pair.intrinsics), c2w, torch.rand(1, 4, 5, 3), keyframe=1)
    (g.means.sum() + g.scales.sum()).backward()
    assert depth.grad is not None and depth.grad.abs().min() > 0


def _recon(with_maps: bool = True) -> Reconstruction:
    pair = make_pair(num_views=3, height=6, width=8)
    maps = {}
    if with_maps:
        maps = dict(depth=pair.gt_depth, rigid_flow=pair.gt_flow, residual_flow=pair.gt_flow * 0.1)
    return Reconstruction.from_pair(
        pair, random_gaussians(40, degree=1), sky_sh=torch.rand(9, 3), meta={"method": "test"}, **maps
    )


@pytest.mark.parametrize("precision", ["float32", "float16"])
def test_recon_round_trip_is_exact_up_to_the_stored_precision(tmp_path, precision):
    from drivingscene.gaussians.recon import HALF

    recon = _recon()
    back = load_reconstruction(save_reconstruction(recon, tmp_path / "r.npz", precision=precision))
    for name in ("means", "quats", "log_scales", "opacity_logits", "sh", "flows", "keyframes", "cameras"):
        want = getattr(recon.gaussians, name)
        if precision == "float16" and name in HALF:
            want = want.half().float()  # rounded to float16 once, read back as float32
        assert getattr(back.gaussians, name).dtype == want.dtype
        torch.testing.assert_close(getattr(back.gaussians, name), want, atol=0, rtol=0)
    np.testing.assert_array_equal(back.depth, recon.depth)
    np.testing.assert_array_equal(back.total_flow, recon.rigid_flow + recon.residual_flow)  # the maps stay float32
    assert back.meta == {"method": "test"} and back.camera_names == recon.camera_names
    torch.testing.assert_close(back.sky_sh, recon.sky_sh)


def test_version_1_files_are_read_and_unknown_versions_refused(tmp_path):
    recon = _recon()
    arrays = recon_to_arrays(recon)  # float32: the version-1 layout
    arrays["version"] = np.array(1, np.int64)
    save_npz(tmp_path / "v1.npz", arrays)
    back = load_reconstruction(tmp_path / "v1.npz")
    torch.testing.assert_close(back.gaussians.quats, recon.gaussians.quats, atol=0, rtol=0)
    arrays["version"] = np.array(3, np.int64)
    save_npz(tmp_path / "v3.npz", arrays)
    with pytest.raises(SceneFormatError, match=r"v3.npz: version: expected one of \[1, 2\]"):
        load_reconstruction(tmp_path / "v3.npz")


def test_static_gaussians_carry_no_flow_in_the_file():
    recon = _recon(with_maps=False)
    arrays = recon_to_arrays(recon)
    assert arrays["dynamic_index"].size == int(recon.gaussians.dynamic.sum()) < len(recon.gaussians)
    assert arrays["dynamic_flows"].shape == (arrays["dynamic_index"].size, 3)
    assert "flows" not in arrays


def test_camera_poses_interpolate_between_keyframes():
    recon = _recon(with_maps=False)
    mid = recon.cam_to_world_at(0.5)
    c0, c1 = recon.cam_to_world_at(0.0), recon.cam_to_world_at(1.0)
    torch.testing.assert_close(mid[:, :3, 3], (c0[:, :3, 3] + c1[:, :3, 3]) / 2)
    assert mid.shape == (3, 4, 4)


@pytest.mark.parametrize(
    "key, value, message",
    [
        ("log_scales", lambda a: a + np.inf, "log_scales: expected finite values"),
        ("opacity_logits", lambda a: a * np.nan, "opacity_logits: expected numbers"),
        ("keyframes", lambda a: a + 2, "keyframes: expected 0 or 1"),
        ("dynamic_index", lambda a: a + 1000, "dynamic_index: expected unique indices"),
        ("means", lambda a: a[:-1], "means: expected shape [N=40, 3]"),
        ("sh", lambda a: np.concatenate([a, a[:, :1]], 1), "sh: expected 1, 4, 9 or 16"),
        ("means", lambda a: a * np.nan, "means: expected finite values"),
        ("meta", lambda a: np.array("{not json"), "meta: expected a JSON object"),
        ("format", lambda a: np.array("drivingscene/frame-pair"), 'format: expected "drivingscene/reconstruction"'),
    ],
)
def test_recon_validation_errors(tmp_path, key, value, message):
    arrays = recon_to_arrays(_recon())
    arrays[key] = value(arrays[key])
    problems = validate_recon_arrays(arrays, "r.npz")
    assert any(message in str(p) for p in problems), [str(p) for p in problems]
    save_npz(tmp_path / "r.npz", arrays)
    with pytest.raises(SceneFormatError):
        load_reconstruction(tmp_path / "r.npz")


def _plane_depth(normal, offset, k, height, width):
    """z-depth of the plane n . p = offset seen by a camera at the origin (ray-plane intersection)."""
    v, u = torch.meshgrid(torch.arange(height, dtype=torch.float64), torch.arange(width, dtype=torch.float64), indexing="ij")
    rays = torch.stack([(u - k[0, 2]) / k[0, 0], (v - k[1, 2]) / k[1, 1], torch.ones_like(u)], -1)
    return offset / (rays @ normal)


def test_default_surfels_lie_in_the_surface_and_project_to_round_pixel_splats():
    from drivingscene.gaussians.assembly import MIN_COS, surface_normals
    from drivingscene.geometry.se3 import quat_to_matrix as q2m
    from drivingscene.render.project import covariances_3d, project_covariances

    k = torch.tensor([[60.0, 0, 23.5], [0, 60.0, 15.5], [0, 0, 1]], dtype=torch.float64)
    normal = torch.nn.functional.normalize(torch.tensor([0.0, -1.0, -0.6], dtype=torch.float64), dim=0)  # a road-like plane
    depth = _plane_depth(normal, -1.5, k, 32, 48)[None]
    assert (depth > 0).all()
    points = unproject(depth, k[None])
    torch.testing.assert_close(surface_normals(points)[0], normal.expand(32, 48, 3), atol=1e-6, rtol=0)
    g = gaussians_from_pixels(
        depth,
        k[None],
        torch.eye(4, dtype=torch.float64)[None],
        torch.rand(1, 32, 48, 3, dtype=torch.float64),
        keyframe=0,
        footprints=None,
    )
    torch.testing.assert_close((q2m(g.quats)[:, :, 2] @ normal).abs(), torch.ones(len(g), dtype=torch.float64), atol=1e-6, rtol=0)
    proj = project_covariances(
        g.means, covariances_3d(g.quats, g.scales), torch.eye(4, dtype=torch.float64), k, 48, 32, eps2d=0.0
    )
    a, b, c = proj.conics.unbind(-1)
    cov = torch.stack([c, -b, -b, a], -1).view(-1, 2, 2) / (a * c - b * b)[:, None, None]
    eig = torch.linalg.eigvalsh(cov)
    # In its own view every surfel is a round splat of FOOTPRINT pixels (sigma), whatever the slant
    # (this plane is never grazing enough to reach the MIN_COS cap); the thin normal axis adds <1%.
    torch.testing.assert_close(eig.sqrt(), torch.full_like(eig, FOOTPRINT), rtol=1e-2, atol=0)
    assert (eig.sqrt() - FOOTPRINT).abs().min() < 1e-6  # the axis in the surface is exact
    assert MIN_COS > 0


def _own_view_cov(g, k):
    """``[N, 2, 2]`` 2D covariances (px^2, no low-pass) of Gaussians seen by a camera at the origin."""
    from drivingscene.render.project import covariances_3d, project_covariances

    proj = project_covariances(
        g.means, covariances_3d(g.quats, g.scales), torch.eye(4, dtype=torch.float64), k, 48, 32, eps2d=0.0
    )
    a, b, c = proj.conics.unbind(-1)
    return torch.stack([c, -b, -b, a], -1).view(-1, 2, 2) / (a * c - b * b)[:, None, None]


def test_the_footprint_rule_widens_every_splat_by_the_floor_and_caps_wide_ones():
    from drivingscene.gaussians.assembly import FOOTPRINT_FLOOR, MAX_FOOTPRINT

    k = torch.tensor([[60.0, 0, 23.5], [0, 60.0, 15.5], [0, 0, 1]], dtype=torch.float64)
    normal = torch.nn.functional.normalize(torch.tensor([0.0, -1.0, -0.6], dtype=torch.float64), dim=0)
    depth = _plane_depth(normal, -1.5, k, 32, 48)[None]
    eye, colors = torch.eye(4, dtype=torch.float64)[None], torch.rand(1, 32, 48, 3, dtype=torch.float64)
    plain = gaussians_from_pixels(depth, k[None], eye, colors, keyframe=0, footprints=None)
    ruled = gaussians_from_pixels(depth, k[None], eye, colors, keyframe=0)
    # the floor is an isotropic 3D variance floor * (z / f)^2: in the own view J J^T (z/f)^2 * floor more
    points = unproject(depth, k[None]).reshape(-1, 3)
    x, y, z = points.unbind(-1)
    jac = torch.stack([torch.stack([60 / z, 0 * z, -60 * x / z**2], -1), torch.stack([0 * z, 60 / z, -60 * y / z**2], -1)], -2)
    expected = _own_view_cov(plain, k) + FOOTPRINT_FLOOR * (z / 60.0)[:, None, None] ** 2 * (jac @ jac.transpose(-1, -2))
    torch.testing.assert_close(_own_view_cov(ruled, k), expected, rtol=1e-6, atol=1e-9)
    # a Gaussian far wider than its pixel (P may make one) is shrunk, shape kept, to MAX_FOOTPRINT
    wide = torch.log(torch.tensor([6.0, 3.0, 0.1], dtype=torch.float64) * 5.0 / 60.0).expand(1, 32, 48, 3)
    quats = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=torch.float64).expand(1, 32, 48, 4)
    capped = gaussians_from_pixels(depth, k[None], eye, colors, keyframe=0, log_scales=wide, quats=quats)
    unfloored = torch.exp(2 * capped.log_scales) - FOOTPRINT_FLOOR * (z / 60.0)[:, None] ** 2
    largest = torch.linalg.eigvalsh(_own_view_cov(replace(capped, log_scales=0.5 * torch.log(unfloored)), k))[:, -1]
    torch.testing.assert_close(largest.sqrt(), torch.full_like(largest, MAX_FOOTPRINT), rtol=1e-6, atol=0)
    ratios = unfloored / unfloored[:, :1]
    torch.testing.assert_close(
        ratios, torch.tensor([1.0, 0.25, (0.1 / 6.0) ** 2], dtype=torch.float64).expand_as(ratios), rtol=1e-6, atol=0
    )


@pytest.mark.parametrize("rule", [(0.5, 0.2), (0.0, 0.2), (0.5, 0.0), (1.0, 0.3)])
def test_compiled_footprint_rule_matches_the_torch_path(rule):
    from drivingscene import kernels
    from drivingscene.gaussians.assembly import FootprintRule, pixel_footprints

    g = torch.Generator().manual_seed(5)
    depth = torch.rand(3, 17, 29, generator=g) * 40.0
    depth[0, 0, :5] = 0.0  # below the clamp
    k = torch.tensor([[[55.0, 0.4, 14.0], [0, 58.0, 8.5], [0, 0, 1]], [[40.0, 0, 15.0], [0, 40.0, 9.0], [0, 0, 1]]] * 2)[:3]
    quats = torch.randn(3, 17, 29, 4, generator=g)
    log_scales = torch.randn(3, 17, 29, 3, generator=g) - 2.0
    log_scales[1, :, :, 1] = log_scales[1, :, :, 0]
    rule = FootprintRule(*rule)
    assert kernels.available(kernels.pixel_footprints, "auto", depth, k, quats, log_scales)
    compiled = pixel_footprints(depth, k, quats, log_scales, rule)
    reference = pixel_footprints(depth, k, quats, log_scales, rule, backend="torch")
    torch.testing.assert_close(compiled, reference, rtol=0, atol=2e-5)
    assert not torch.equal(reference, log_scales)  # the rule changed them


def test_transform_moves_means_flows_and_rotations_consistently():
    from drivingscene.geometry import quat_to_matrix as q2m

    g = random_gaussians(20)
    yaw = 0.7
    mat = torch.eye(4, dtype=torch.float64)
    mat[:2, :2] = torch.tensor([[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]])
    mat[:3, 3] = torch.tensor([100.0, -20.0, 3.0])
    moved = g.transform(mat)
    rot = mat[:3, :3].float()
    torch.testing.assert_close(moved.means, g.means @ rot.T + mat[:3, 3].float())
    torch.testing.assert_close(moved.flows, g.flows @ rot.T)
    torch.testing.assert_close(q2m(moved.quats), rot @ q2m(g.quats), atol=1e-6, rtol=0)
    torch.testing.assert_close(moved.transform(torch.linalg.inv(mat)).means, g.means, atol=1e-4, rtol=0)


def test_axes_to_quat_gives_an_equivalent_gaussian_with_w_at_least_half():
    from drivingscene.gaussians.assembly import axes_to_quat
    from drivingscene.geometry.se3 import quat_to_matrix as q2m

    rot = q2m(torch.nn.functional.normalize(torch.randn(500, 4, dtype=torch.float64), dim=-1))
    rot = torch.cat([rot, torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64))[None]])  # 180 degrees
    q = axes_to_quat(rot)
    assert (q[:, 0] >= 0.5 - 1e-9).all()
    back = q2m(q)
    # Same axes up to sign: the covariance R S^2 R^T is unchanged.
    scales = torch.diag(torch.tensor([0.3, 1.0, 2.0], dtype=torch.float64)) ** 2
    torch.testing.assert_close(back @ scales @ back.transpose(1, 2), rot @ scales @ rot.transpose(1, 2))


def test_compiled_surfel_frames_match_the_torch_path():
    from drivingscene import kernels
    from drivingscene.gaussians.assembly import surfel_frames, surfel_frames_torch
    from drivingscene.geometry.se3 import quat_to_matrix as q2m

    if not kernels.load_extension():
        pytest.skip("C++ kernels unavailable (no compiler/ninja; see the logged warning)")
    g = torch.Generator().manual_seed(0)
    # Blocky depth with edges, slanted planes and near/far jumps, in 3 cameras with skew and offsets.
    depth = 2.0 + 60.0 * torch.rand(3, 6, 8, generator=g).repeat_interleave(5, 1).repeat_interleave(5, 2)
    depth = depth + torch.linspace(0, 4, 40)[None, None, :] + 0.05 * torch.rand(3, 30, 40, generator=g)
    k = (
        torch.tensor([[[50.0, 0.3, 19.5], [0.0, 48.0, 14.5], [0, 0, 1]]]).repeat(3, 1, 1)
        * torch.tensor([1.0, 1.2, 0.8])[:, None, None]
    )
    k[:, 2, 2] = 1
    q_cpp, s_cpp = surfel_frames(depth, k, backend="cpp")
    q_ref, s_ref = surfel_frames_torch(depth, k)
    torch.testing.assert_close(s_cpp, s_ref, atol=1e-4, rtol=0)

    def cov(q, s):
        r = q2m(q)
        return r @ torch.diag_embed(torch.exp(2 * s)) @ r.transpose(-1, -2)

    c_cpp, c_ref = cov(q_cpp, s_cpp), cov(q_ref, s_ref)
    rel = (c_cpp - c_ref).abs().amax((-1, -2)) / c_ref.abs().amax((-1, -2))
    assert rel.max() < 1e-4
    torch.testing.assert_close(q_cpp.norm(dim=-1), torch.ones(3, 30, 40), atol=1e-5, rtol=0)
    # "auto" takes the compiled path for float32 CPU input and the torch path for float64.
    torch.testing.assert_close(surfel_frames(depth, k)[1], s_cpp, atol=0, rtol=0)
    assert surfel_frames(depth.double(), k.double())[1].dtype == torch.float64


def test_sky_pixel_directions_match_the_full_ray_grid():
    from drivingscene.render.sky import pixel_directions, ray_directions

    k = torch.tensor([[40.0, 0.5, 15.5], [0.0, 38.0, 11.5], [0.0, 0.0, 1.0]], dtype=torch.float64)
    cam = torch.eye(4, dtype=torch.float64)
    cam[:3, :3] = torch.linalg.qr(torch.randn(3, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(1)))[0]
    mask = torch.rand(24, 32, generator=torch.Generator().manual_seed(2)) < 0.3
    torch.testing.assert_close(pixel_directions(cam, k, mask), ray_directions(cam[None], k[None], 24, 32)[0][mask])


def test_ground_colour_is_the_median_of_the_gaussians_on_the_road_plane():
    from drivingscene.gaussians.ground import GROUND_BAND, GROUND_MIN_GAUSSIANS, fit_ground, road_plane

    ego = torch.eye(4, dtype=torch.float64)
    ego[:3, 3] = torch.tensor([3.0, -2.0, 1.5])  # the ego frame's z = 0 is the world's z = 1.5
    plane = road_plane(ego)
    torch.testing.assert_close(plane, torch.tensor([0.0, 0.0, 1.0, -1.5]))
    g = torch.Generator().manual_seed(0)
    n = 3 * GROUND_MIN_GAUSSIANS
    on = torch.cat([torch.randn(n, 2, generator=g) * 10, 1.5 + (torch.rand(n, 1, generator=g) - 0.5) * GROUND_BAND], 1)
    off = on + torch.tensor([0.0, 0.0, 3.0])  # a wall's colour above the road
    rgb_on = torch.tensor([0.3, 0.3, 0.35]) + torch.randn(n, 3, generator=g) * 0.02
    rgb_on[:10] = torch.tensor([1.0, 1.0, 0.0])  # lane paint: a few outliers the median ignores
    ground = fit_ground(torch.cat([on, off]), torch.cat([rgb_on, torch.full((n, 3), 0.9)]), plane)
    torch.testing.assert_close(ground.rgb, torch.tensor([0.3, 0.3, 0.35]), atol=0.01, rtol=0)
    assert fit_ground(off, torch.full((n, 3), 0.9), plane) is None  # nothing on the road: no ground


def test_ground_shows_where_rays_descend_from_a_camera_above_the_plane():
    from drivingscene.gaussians.ground import Ground
    from drivingscene.render.scene import background_colors
    from drivingscene.render.sky import HORIZON_BAND, ray_directions, sky_colors

    k = torch.tensor([[[20.0, 0.0, 15.5], [0.0, 20.0, 11.5], [0.0, 0.0, 1.0]]])
    # a camera looking along world +x, its image y axis along world -z (down), 1.5 m above z = 0
    c2w = torch.eye(4)
    c2w[:3, :3] = torch.tensor([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    c2w[2, 3] = 1.5
    sky_sh = torch.randn(9, 3, generator=torch.Generator().manual_seed(3)) * 0.2
    ground = Ground(torch.tensor([0.0, 0.0, 1.0, 0.0]), torch.tensor([0.25, 0.5, 0.75]))
    out = background_colors(torch.linalg.inv(c2w)[None], k, 24, 32, sky_sh, ground=ground)[0]
    dirs = ray_directions(c2w[None], k, 24, 32)[0]
    sky = sky_colors(sky_sh, dirs)
    below = dirs[..., 2] < -HORIZON_BAND
    rising = dirs[..., 2] >= 0
    assert below.any() and rising.any()
    torch.testing.assert_close(out[below], ground.rgb.expand(int(below.sum()), 3))
    torch.testing.assert_close(out[rising], sky[rising])
    # a camera under the plane sees the sky everywhere
    c2w[2, 3] = -0.5
    under = background_colors(torch.linalg.inv(c2w)[None], k, 24, 32, sky_sh, ground=ground)[0]
    torch.testing.assert_close(under, sky_colors(sky_sh, ray_directions(c2w[None], k, 24, 32)[0]))


def test_recon_ground_is_stored_and_fitted_for_files_without_it(tmp_path):
    pair = make_pair(num_views=3, height=6, width=8)
    plane_z = float(pair.ego_to_world[0, 2, 3])
    g = torch.Generator().manual_seed(4)
    gaussians = random_gaussians(400)
    means = gaussians.means.clone()
    means[:200, 2] = plane_z  # half of them on the road plane (the ego frame is z-up, level)
    rgb = torch.full((400, 3), 0.8)
    rgb[:200] = torch.tensor([0.2, 0.4, 0.3]) + torch.rand(200, 3, generator=g) * 0.01
    from drivingscene.gaussians.core import rgb_to_sh0

    gaussians = replace(gaussians, means=means, sh=rgb_to_sh0(rgb)[:, None])
    recon = Reconstruction.from_pair(pair, gaussians, sky_sh=torch.rand(9, 3))
    torch.testing.assert_close(recon.ground.rgb, torch.tensor([0.2, 0.4, 0.3]), atol=0.011, rtol=0)
    assert Reconstruction.from_pair(pair, gaussians).ground is None  # no sky model: no ground either
    arrays = recon_to_arrays(recon)
    torch.testing.assert_close(load_reconstruction(save_reconstruction(recon, tmp_path / "r.npz")).ground_rgb, recon.ground_rgb)
    del arrays["ground_rgb"]  # a file written before the ground existed: fitted on load
    save_npz(tmp_path / "old.npz", arrays)
    torch.testing.assert_close(load_reconstruction(tmp_path / "old.npz").ground_rgb, recon.ground_rgb)


def _view_bound(g: Gaussians, every: int = 3) -> Gaussians:
    """``g`` with every ``every``-th Gaussian view-bound along a random unit ray."""
    rays = torch.nn.functional.normalize(torch.randn(len(g), 3, generator=torch.Generator().manual_seed(4)), dim=-1)
    rays[torch.arange(len(g)) % every != 0] = 0
    return replace(g, view_rays=rays)


def test_view_rays_default_to_zero_and_travel_with_the_gaussians():
    g = random_gaussians(30)
    assert g.view_rays.shape == (30, 3) and not g.view_bound.any()
    b = _view_bound(g)
    assert int(b.view_bound.sum()) == 10
    torch.testing.assert_close(b.index(torch.arange(0, 30, 3)).view_rays, b.view_rays[::3])
    assert Gaussians.cat([g, b]).view_bound.sum() == 10
    # a rigid transform turns the rays with the frame: the angle to each mean's offset is kept
    a_to_b = torch.eye(4, dtype=torch.float64)
    a_to_b[:3, :3] = quat_to_matrix(torch.nn.functional.normalize(torch.tensor([0.9, 0.1, -0.3, 0.2]), dim=0)).double()
    a_to_b[:3, 3] = torch.tensor([1.0, -2.0, 0.5])
    moved = b.transform(a_to_b)
    torch.testing.assert_close(moved.view_rays, b.view_rays @ a_to_b[:3, :3].T.float())
    assert torch.equal(moved.view_bound, b.view_bound)
    with pytest.raises(InputError, match="view_rays"):
        replace(g, view_rays=torch.zeros(29, 3))


def test_view_fade_is_full_near_the_view_ray_and_zero_far_from_it():
    from drivingscene.gaussians.core import VIEW_FADE_DEG, view_fade

    centre = torch.zeros(3)
    means = torch.tensor([[0.0, 0.0, 10.0]]).expand(6, 3)
    degrees = torch.tensor([0.0, VIEW_FADE_DEG[0], 0.5 * sum(VIEW_FADE_DEG), VIEW_FADE_DEG[1], 45.0, 90.0])
    rays = torch.stack([torch.sin(torch.deg2rad(degrees)), torch.zeros(6), torch.cos(torch.deg2rad(degrees))], -1)
    fade = view_fade(rays, means, centre)
    torch.testing.assert_close(fade[[0, 1]], torch.ones(2), atol=1e-5, rtol=0)
    assert 0.2 < fade[2] < 0.8
    torch.testing.assert_close(fade[3:], torch.zeros(3), atol=1e-5, rtol=0)
    torch.testing.assert_close(view_fade(torch.zeros(6, 3), means, centre), torch.ones(6))  # not view-bound


def test_recon_view_rays_round_trip_and_bad_rays_are_named(tmp_path):
    recon = _recon()
    recon = recon.with_gaussians(_view_bound(recon.gaussians))
    arrays = recon_to_arrays(recon)
    assert arrays["view_bound_index"].size == int(recon.gaussians.view_bound.sum()) > 0
    back = load_reconstruction(save_reconstruction(recon, tmp_path / "r.npz"))
    torch.testing.assert_close(back.gaussians.view_rays, recon.gaussians.view_rays, atol=0, rtol=0)
    assert "view_bound_index" not in recon_to_arrays(_recon())  # none: the keys are left out
    bad = dict(arrays, view_bound_rays=arrays["view_bound_rays"] * 2)
    assert any("view_bound_rays: expected unit vectors" in str(p) for p in validate_recon_arrays(bad, "r.npz"))
    lone = {k: v for k, v in arrays.items() if k != "view_bound_rays"}
    assert any(
        "view_bound_rays: expected view_bound_index and view_bound_rays together" in str(p)
        for p in validate_recon_arrays(lone, "r.npz")
    )
