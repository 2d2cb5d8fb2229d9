"""The GL splat renderer against the torch rasterizer (same Gaussian model), and sort correctness."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch
from drivingscene_view.camera import rig_camera
from drivingscene_view.renderer import GpuSplats, RenderOptions, SplatRenderer
from drivingscene_view.sorter import SortRequest, depth_order, layer_ids, make_sort_input
from drivingscene_view.splats import SplatArrays

from drivingscene.gaussians.ground import Ground
from drivingscene.gaussians.timing import LAYERED_BLENDS
from drivingscene.render.scene import LayerBlend, render_gaussians
from tests.app.scenes import random_gaussians

W, H = 96, 64
K = np.array([[80.0, 0.0, 47.3], [0.0, 78.0, 31.8], [0.0, 0.0, 1.0]])


def _camera():
    c2w = np.eye(4)
    c2w[:3, 3] = [0.2, -0.1, 0.3]
    return rig_camera(c2w, K, (H, W))


def _gl_render(ctx, gaussians, sky, t, blend, keys, mode="rgb", axes=None, ground=None, layer_blend=None, centres=None):
    renderer, gpu = SplatRenderer(ctx), GpuSplats(ctx)
    splats = SplatArrays.from_gaussians(gaussians)
    gpu.set_splats(splats, origin=np.array([0.1, 0.2, 3.0]))
    renderer.set_sky(sky.numpy())
    renderer.set_ground(ground)
    renderer.set_cameras(axes, centres)
    cam = _camera()
    req = SortRequest(cam.shifted(gpu.origin).world_to_cam, cam.intrinsics, W, H, t, blend, keys=keys)
    gpu.set_order(depth_order(make_sort_input(splats, gpu.origin), req))
    opts = RenderOptions(blend=blend) if layer_blend is None else RenderOptions(blend=blend, layer_blend=layer_blend)
    if mode == "depth":
        out = renderer.render(gpu, cam, t, RenderOptions(mode="depth", blend=blend)).read()
    else:
        out = renderer.render_image(gpu, cam, t, opts) / 255.0
        # Drawing the same order in chunks (progressive refinement) gives the same picture, whether
        # or not the chunks before the last resolve the layers over the sky; each call says how many
        # splats it drew (each layer's front-depth pass counted: what the viewport sizes chunks by).
        for every in (1, 3, gpu.count + 1):  # resolved on every chunk, on every third, on the last only
            target = renderer.target(W, H, name=f"chunks{every}")
            drawn = 0
            for i, start in enumerate(range(0, gpu.count, 37)):
                renderer.render_range(gpu, cam, t, opts, target, start, 37, resolve=i % every == 0)
                drawn += renderer.last_drawn
            np.testing.assert_allclose(target.read()[..., :3], renderer.render(gpu, cam, t, opts).read()[..., :3], atol=1e-3)
            surfaces = blend in LAYERED_BLENDS and opts.layer_blend.surface_tolerance > 0
            assert drawn == gpu.count * (2 if surfaces else 1)
    renderer.release()
    gpu.release()
    return out


def _three_cameras(gaussians):
    """``gaussians`` split among three source cameras, the third with unknown (-1) splats as well,
    with their axes ``[2, 3, 3]`` (0, 40 and 80 degrees off the view, 10 degrees more at keyframe 1)
    and a sky."""
    gaussians = dataclasses.replace(gaussians, cameras=torch.arange(len(gaussians)) % 4 - 1)
    rad = np.radians([[0.0, 40.0, 80.0], [10.0, 50.0, 90.0]])
    axes = np.stack([np.sin(rad), np.zeros_like(rad), np.cos(rad)], -1)
    return gaussians, axes, torch.randn(9, 3, generator=torch.Generator().manual_seed(1)) * 0.3


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    return 10 * math.log10(1.0 / max(float(((a - b) ** 2).mean()), 1e-12))


@pytest.mark.gl
@pytest.mark.parametrize(
    "sh_degree, t, blend, keys",
    [
        (0, 0.0, "all", "u16"),
        (1, 0.3, "all", "u16"),
        (3, 0.7, "fade", "float"),
        (2, 0.6, "nearest", "u16"),
        (0, 0.4, "layers", "u16"),
        (1, 0.3, "cameras", "u16"),
        (2, 0.0, "cameras", "float"),  # a keyframe: the other one only fills, and mixes in off its cameras' axes
    ],
)
def test_gl_matches_torch_rasterizer(gl_ctx, sh_degree, t, blend, keys):
    gaussians = random_gaussians(300, sh_degree=sh_degree, seed=sh_degree)
    gaussians, axes, sky = _three_cameras(gaussians)
    cam = _camera()
    ref = (
        render_gaussians(
            gaussians,
            t,
            torch.from_numpy(cam.world_to_cam)[None].float(),
            torch.from_numpy(K)[None].float(),
            H,
            W,
            sky_sh=sky,
            blend=blend,
            source_axes=torch.from_numpy(axes).float(),
            max_layers=1024,
            backend="torch",
        )
        .colors[0]
        .clamp(0, 1)
        .numpy()
    )
    gl = _gl_render(gl_ctx, gaussians, sky, t, blend, keys, axes=axes)
    assert _psnr(gl, ref) >= 35.0
    assert ref.std() > 0.05  # the scene is not trivially empty


@pytest.mark.gl
def test_gl_mixes_the_keyframes_as_torch(gl_ctx):
    # at a keyframe, layers whose cameras look away from the view: how much of the other keyframe
    # mixes in (LayerBlend.far_mix) is the CPU renderer's in the window too
    gaussians = random_gaussians(300, sh_degree=2, seed=2)
    gaussians, axes, sky = _three_cameras(gaussians)
    cam = _camera()
    rules = [LayerBlend(far_mix=0.0), LayerBlend(far_mix=1.0)]
    refs = [
        render_gaussians(
            gaussians, 0.0, torch.from_numpy(cam.world_to_cam)[None].float(), torch.from_numpy(K)[None].float(), H, W,
            sky_sh=sky, blend="cameras", source_axes=torch.from_numpy(axes).float(), max_layers=1024, backend="torch",
            layer_blend=rule,
        ).colors[0].clamp(0, 1).numpy()
        for rule in rules
    ]  # fmt: skip
    assert _psnr(*refs) < 35.0  # the rule changes the picture
    for rule, ref, other in zip(rules, refs, refs[::-1]):
        gl = _gl_render(gl_ctx, gaussians, sky, 0.0, "cameras", "float", axes=axes, layer_blend=rule)
        assert _psnr(gl, ref) >= 40.0 and _psnr(gl, ref) > _psnr(gl, other) + 5.0


@pytest.mark.gl
def test_gl_sharpens_near_a_source_camera_as_torch(gl_ctx):
    # mid-way, a view standing where the layers' cameras stood (a still ego) weighs them as sharply
    # as at their keyframe (LayerBlend.pose_scale); the window draws what the CPU renderer does
    gaussians = random_gaussians(300, sh_degree=2, seed=3)
    gaussians, axes, sky = _three_cameras(gaussians)
    cam = _camera()
    here = np.broadcast_to(np.linalg.inv(cam.world_to_cam)[:3, 3], (2, 3, 3)).copy()
    cases = [here, here + np.array([0.0, 5.0, 0.0])]  # at the view's centre, and 5 m away (time alone)
    refs = [
        render_gaussians(
            gaussians, 0.5, torch.from_numpy(cam.world_to_cam)[None].float(), torch.from_numpy(K)[None].float(), H, W,
            sky_sh=sky, blend="cameras", source_axes=torch.from_numpy(axes).float(), source_centres=torch.from_numpy(centres),
            max_layers=1024, backend="torch",
        ).colors[0].clamp(0, 1).numpy()
        for centres in cases
    ]  # fmt: skip
    assert _psnr(*refs) < 35.0  # the centres change the picture
    for centres, ref, other in zip(cases, refs, refs[::-1]):
        gl = _gl_render(gl_ctx, gaussians, sky, 0.5, "cameras", "float", axes=axes, centres=centres)
        assert _psnr(gl, ref) >= 40.0 and _psnr(gl, ref) > _psnr(gl, other) + 5.0


@pytest.mark.gl
def test_gl_expected_depth_matches_torch(gl_ctx):
    gaussians = random_gaussians(200, sh_degree=0, seed=5)
    cam = _camera()
    ref = render_gaussians(
        gaussians,
        0.5,
        torch.from_numpy(cam.world_to_cam)[None].float(),
        torch.from_numpy(K)[None].float(),
        H,
        W,
        max_layers=1024,
        backend="torch",
    )
    out = _gl_render(gl_ctx, gaussians, torch.zeros(1, 3), 0.5, "all", "float", mode="depth")
    alpha = ref.alphas[0].numpy()
    np.testing.assert_allclose(out[..., 3], alpha, atol=2e-3)
    solid = alpha > 0.5
    depth = out[..., 0][solid] / out[..., 3][solid]
    np.testing.assert_allclose(depth, ref.depths[0].numpy()[solid], rtol=2e-3)


def test_sort_matches_float_argsort():
    splats = SplatArrays.from_gaussians(random_gaussians(2000, seed=3))
    cam = _camera()
    data = make_sort_input(splats, np.zeros(3))
    for t in (0.0, 0.4, 1.0):
        req = SortRequest(cam.world_to_cam, K, W, H, t, keys="float")
        order = depth_order(data, req)
        z = splats.means_at(t).astype(np.float64) @ cam.world_to_cam[2, :3] + cam.world_to_cam[2, 3]
        # Exactly the float argsort of the visible splats' depths (stable: ties by index).
        np.testing.assert_array_equal(order, np.sort(order)[np.argsort(z[np.sort(order)], kind="stable")])
        assert np.all(np.diff(z[order]) >= 0)
        u16 = depth_order(data, SortRequest(cam.world_to_cam, K, W, H, t, keys="u16"))
        assert set(u16.tolist()) == set(order.tolist())
        # 16-bit log-depth buckets: any inversion is within one bucket (relative depth 1e-4 here).
        zs = z[u16]
        assert np.all(np.diff(np.log(zs)) >= -np.log(zs.max() / zs.min()) / 65535 * 1.01)


def test_layered_blends_sort_each_layer_front_to_back():
    g = random_gaussians(2000, seed=3)
    g = dataclasses.replace(g, cameras=torch.arange(len(g)) % 3 - 1)
    splats = SplatArrays.from_gaussians(g)
    cam = _camera()
    data = make_sort_input(splats, np.zeros(3))
    plain = depth_order(data, SortRequest(cam.world_to_cam, K, W, H, 0.3, keys="float"))
    order = depth_order(data, SortRequest(cam.world_to_cam, K, W, H, 0.3, blend="cameras", keys="float"))
    assert set(order.tolist()) == set(plain.tolist())
    keys = splats.keyframes[order].astype(int) * 10 + splats.cameras[order]
    assert np.all(np.diff(keys) >= 0)  # grouped: keyframe, then camera
    z = splats.means_at(0.3).astype(np.float64) @ cam.world_to_cam[2, :3]
    for key in np.unique(keys):  # each group in the plain order's (front-to-back) order
        np.testing.assert_array_equal(order[keys == key], plain[np.isin(plain, order[keys == key])])
        assert np.all(np.diff(z[order[keys == key]]) >= 0)
    gpu_segments = GpuSplats.__new__(GpuSplats)
    gpu_segments.layer_ids = layer_ids(splats.keyframes, splats.cameras)
    segments = gpu_segments._segments(order)
    assert [(k, c) for k, c, _, _ in segments] == sorted(
        {(int(k), int(c)) for k, c in zip(splats.keyframes[order], splats.cameras[order])}
    )
    assert segments[0][2] == 0 and segments[-1][3] == len(order)
    assert gpu_segments._segments(plain) is None  # a plain depth order is not grouped


def test_sort_culls_conservatively():
    """Everything the exact projection draws survives the sort's cull; hidden and behind-camera do not."""
    from drivingscene.render.project import project_gaussians

    g = random_gaussians(3000, seed=4)
    g = type(g)(**{**{f: getattr(g, f) for f in g.__dataclass_fields__}, "means": g.means * torch.tensor([6.0, 6.0, 2.0])})
    splats = SplatArrays.from_gaussians(g)
    cam = _camera()
    hidden = np.zeros(len(splats), bool)
    hidden[::7] = True
    order = depth_order(make_sort_input(splats, np.zeros(3), hidden), SortRequest(cam.world_to_cam, K, W, H, 0.0, keys="float"))
    proj = project_gaussians(
        g.means_at(0.0),
        g.quats,
        g.scales,
        torch.from_numpy(cam.world_to_cam)[None].float(),
        torch.from_numpy(K)[None].float(),
        W,
        H,
    )
    drawn = set(np.flatnonzero((proj.radii[0] > 0).numpy() & ~hidden).tolist())
    assert drawn <= set(order.tolist())
    assert not hidden[order].any()
    assert len(order) < len(splats) * 0.9  # something was culled


@pytest.mark.gl
def test_gl_ground_matches_torch(gl_ctx):
    """The ground below the horizon: the same background in the window as in the CPU renderer, with
    the splats' origin shifted (the plane moves with it)."""
    gaussians = random_gaussians(100, sh_degree=0, seed=3)
    sky = torch.randn(9, 3, generator=torch.Generator().manual_seed(2)) * 0.3
    # world y points down in this camera: the plane y = 0.5 lies below it (n = -y, up; d = 0.5)
    ground = Ground(torch.tensor([0.0, -1.0, 0.0, 0.5]), torch.tensor([0.9, 0.2, 0.1]))
    cam = _camera()
    args = (torch.from_numpy(cam.world_to_cam)[None].float(), torch.from_numpy(K)[None].float(), H, W)
    ref = render_gaussians(gaussians, 0.0, *args, sky_sh=sky, ground=ground, max_layers=1024, backend="torch")
    without = render_gaussians(gaussians, 0.0, *args, sky_sh=sky, max_layers=1024, backend="torch")
    ref_img = ref.colors[0].clamp(0, 1).numpy()
    gl = _gl_render(gl_ctx, gaussians, sky, 0.0, "all", "u16", ground=ground)
    assert _psnr(gl, ref_img) >= 35.0
    # the ground shows in the lower half (rays descend), not in the upper half
    bare = ref.alphas[0].numpy() < 1e-4
    lower, upper = bare & (np.arange(H)[:, None] > 0.6 * H), bare & (np.arange(H)[:, None] < 0.3 * H)
    assert lower.any() and upper.any()
    np.testing.assert_allclose(ref_img[lower], np.broadcast_to([0.9, 0.2, 0.1], ref_img[lower].shape), atol=1e-3)
    np.testing.assert_allclose(ref_img[upper], without.colors[0].clamp(0, 1).numpy()[upper], atol=1e-3)


def _with_view_rays(gaussians, centre: np.ndarray, degrees: np.ndarray):
    """``gaussians`` whose view rays are the rays from ``centre`` to them turned by ``degrees`` [N]
    (NaN: not view-bound) about an axis across the ray."""
    to_mean = torch.nn.functional.normalize(gaussians.means - torch.from_numpy(centre).float(), dim=-1)
    across = torch.nn.functional.normalize(torch.cross(to_mean, torch.tensor([0.0, 1.0, 0.0]).expand_as(to_mean), dim=-1), dim=-1)
    angle = torch.from_numpy(np.nan_to_num(np.radians(degrees))).float()[:, None]
    rays = torch.cos(angle) * to_mean + torch.sin(angle) * across
    rays = torch.where(torch.from_numpy(np.isnan(degrees))[:, None], torch.zeros_like(rays), rays)
    return dataclasses.replace(gaussians, view_rays=rays)


@pytest.mark.gl
def test_gl_view_bound_matches_torch(gl_ctx):
    """View-bound Gaussians fade with the angle between the view ray and their own, the same in
    the window as in the CPU renderer: drawn fully within 3 degrees, partly at 12, not at all at 30."""
    gaussians = random_gaussians(120, sh_degree=0, seed=5)
    cam = _camera()
    degrees = np.tile([np.nan, 0.0, 2.0, 12.0, 30.0, 60.0], 20)
    bound = _with_view_rays(gaussians, cam.centre, degrees)
    sky = torch.zeros(1, 3)
    args = (torch.from_numpy(cam.world_to_cam)[None].float(), torch.from_numpy(K)[None].float(), H, W)
    ref = render_gaussians(bound, 0.0, *args, sky_sh=sky, max_layers=1024, backend="torch").colors[0].clamp(0, 1).numpy()
    gl = _gl_render(gl_ctx, bound, sky, 0.0, "all", "u16")
    assert _psnr(gl, ref) >= 35.0
    # the same picture as the Gaussians left without the faded ones, and not the picture of all of them
    faded = np.isin(degrees, [30.0, 60.0])
    kept = torch.from_numpy(~faded & (degrees != 12.0))
    plain = render_gaussians(gaussians, 0.0, *args, sky_sh=sky, max_layers=1024, backend="torch").colors[0].numpy()
    assert _psnr(ref, plain.clip(0, 1)) < 40.0
    partial = render_gaussians(bound.index(~torch.from_numpy(faded)), 0.0, *args, sky_sh=sky, max_layers=1024, backend="torch")
    assert _psnr(ref, partial.colors[0].clamp(0, 1).numpy()) >= 60.0
    half = render_gaussians(gaussians.index(kept), 0.0, *args, sky_sh=sky, max_layers=1024, backend="torch")
    assert _psnr(ref, half.colors[0].clamp(0, 1).numpy()) < 60.0  # the 12-degree ones show, partly
