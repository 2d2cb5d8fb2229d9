"""The textured depth-mesh baseline (drivingscene/methods/depth_mesh.py): a plane renders its own
texture at its own pose, a depth edge leaves a gap instead of a stretched triangle, a moved camera
sees the plane where the geometry says, vertices move with their pixel's Gaussian, and the layers
blend with the Gaussians' "cameras" weights."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from drivingscene.errors import DrivingSceneError
from drivingscene.gaussians.core import Gaussians
from drivingscene.gaussians.recon import Reconstruction
from drivingscene.methods import depth_mesh
from drivingscene.methods.depth_mesh import DepthMeshRenderer, grid_triangles, kept_triangles, pixel_scene_flow
from drivingscene.render import scene as render_scene

pytestmark = pytest.mark.gl
H, W, F = 24, 32, 120.0  # image size and focal length (pixels): a pixel spans 0.5 degrees, as at 320 px wide
K = np.array([[F, 0.0, (W - 1) / 2], [0.0, F, (H - 1) / 2], [0.0, 0.0, 1.0]])


@pytest.fixture(scope="module")
def ctx():
    from drivingscene.gl import create_offscreen_context

    try:
        return create_offscreen_context()
    except DrivingSceneError as e:
        pytest.skip(f"no offscreen OpenGL context: {e}")


def _points(depth: np.ndarray) -> np.ndarray:
    """Camera points ``[H, W, 3]`` of a depth map (camera = world here)."""
    v, u = np.meshgrid(np.arange(H, dtype=np.float64), np.arange(W, dtype=np.float64), indexing="ij")
    return np.stack([(u - K[0, 2]) / F * depth, (v - K[1, 2]) / F * depth, depth], -1)


def make_recon(
    depth0: np.ndarray, image0: np.ndarray, depth1: np.ndarray | None = None, flow: np.ndarray | None = None
) -> Reconstruction:
    """One camera at the world origin looking along +z (identity poses at both keyframes), a
    Gaussian per pixel of keyframe 0 at its depth carrying ``flow`` ``[3]``; keyframe 1 has
    ``depth1`` (default none: no mesh) and the same image."""
    depth1 = np.zeros_like(depth0) if depth1 is None else depth1
    valid = depth0 > 0
    means = torch.from_numpy(_points(depth0)[valid]).float()
    n = len(means)
    flows = torch.zeros(n, 3) if flow is None else torch.tensor(flow, dtype=torch.float32).expand(n, 3).clone()
    gaussians = Gaussians(
        means=means,
        quats=torch.tensor([[1.0, 0, 0, 0]]).expand(n, 4).clone(),
        log_scales=torch.full((n, 3), -3.0),
        opacity_logits=torch.full((n,), 4.0),
        sh=torch.zeros(n, 1, 3),
        flows=flows,
        keyframes=torch.zeros(n, dtype=torch.int64),
        cameras=torch.zeros(n, dtype=torch.int64),
    )
    return Reconstruction(
        gaussians=gaussians,
        intrinsics=K[None].astype(np.float32),
        cam_to_ego=np.eye(4, dtype=np.float32)[None],
        ego_to_world=np.stack([np.eye(4), np.eye(4)]),
        timestamps=np.array([0.0, 0.5]),
        camera_names=("CAM",),
        image_size=(H, W),
        images=np.stack([image0, image0])[:, None],
        depth=np.stack([depth0, depth1])[:, None].astype(np.float32),
    )


def texture(seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (H, W, 3), dtype=np.uint8)


def translated(dx: float = 0.0, dy: float = 0.0, dz: float = 0.0) -> np.ndarray:
    """world_to_cam ``[1, 4, 4]`` of the camera moved by (dx, dy, dz) in its own axes."""
    m = np.eye(4)
    m[:3, 3] = [-dx, -dy, -dz]
    return m[None]


def test_a_plane_renders_its_texture_at_its_own_pose(ctx):
    image = texture()
    recon = make_recon(np.full((H, W), 5.0), image)
    out = depth_mesh.render_depth_meshes(recon, 0.0, translated(), K[None], H, W, ctx=ctx)
    assert out.colors.shape == (1, H, W, 3) and out.coverage.shape == (1, H, W) and out.depths.shape == (1, H, W)
    assert bool((out.coverage == 1).all())  # every pixel, the border ones too
    np.testing.assert_allclose(out.colors[0].numpy(), image / 255.0, atol=1e-4)  # float32 interpolation; a level is 4e-3
    np.testing.assert_allclose(out.depths[0].numpy(), 5.0, rtol=1e-5)


def test_a_depth_edge_leaves_a_gap_not_a_stretched_triangle(ctx):
    depth = np.full((H, W), 10.0)
    depth[8:16, 10:20] = 5.0  # a box in front of a wall
    recon = make_recon(depth, texture(1))
    view = translated(dx=0.25)  # 25 cm to the right: the box moves 6 px, the wall 3 px, a 3 px strip of wall shows
    kept = depth_mesh.render_depth_meshes(recon, 0.0, view, K[None], H, W, ctx=ctx)
    every = depth_mesh.render_depth_meshes(recon, 0.0, view, K[None], H, W, ctx=ctx, max_angle_deg=90.0)
    between = lambda out: int(((out.depths > 5.05) & (out.depths < 9.9)).sum())  # noqa: E731 - neither surface
    assert between(kept) == 0
    assert between(every) > 5  # keeping every triangle stretches them across the edge (the test can fail)
    assert int((kept.coverage == 0).sum()) > 5  # the disoccluded strip: nothing there but the background
    # the grazing test itself: a quad straddling the edge is seen edge-on, a fronto-parallel one face-on
    cam = _points(depth).reshape(-1, 3)
    tris = grid_triangles(H, W)
    keep = kept_triangles(cam, tris)
    straddle = np.ptp(depth.reshape(-1)[tris], axis=1) > 0
    assert not keep[straddle].any() and keep[~straddle].all()


def test_a_moved_camera_sees_the_plane_where_geometry_says(ctx):
    image = np.zeros((H, W, 3), np.uint8)
    image[12, 16] = 255  # one bright pixel at depth 5 m
    recon = make_recon(np.full((H, W), 5.0), image)
    dx = 3 * 5.0 / F  # metres that shift a point at 5 m by 3 px
    out = depth_mesh.render_depth_meshes(recon, 0.0, translated(dx=dx), K[None], H, W, ctx=ctx)
    bright = out.colors[0, ..., 0].numpy()
    v, u = np.unravel_index(np.argmax(bright), bright.shape)
    # the point ((16 - cx) 5 / F, (12 - cy) 5 / F, 5) seen from x = dx: u = 16 - F dx / 5
    assert (v, u) == (12, 13)
    assert bright[12, 13] == pytest.approx(1.0, abs=1e-4)
    np.testing.assert_allclose(out.depths[0][out.coverage[0] > 0].numpy(), 5.0, rtol=1e-4)


def test_vertices_move_with_their_pixels_gaussian(ctx):
    image = np.zeros((H, W, 3), np.uint8)
    image[12, 10] = 255
    step = 2 * 5.0 / F  # everything moves right by 2 px at 5 m between the keyframes
    recon = make_recon(np.full((H, W), 5.0), image, flow=(step, 0.0, 0.0))
    flow = pixel_scene_flow(recon)
    assert flow.shape == (2, 1, H, W, 3)
    np.testing.assert_allclose(flow[0, 0], np.broadcast_to([step, 0.0, 0.0], (H, W, 3)), rtol=1e-6)
    assert not flow[1].any()  # no keyframe-1 Gaussians: zero flow
    renderer = DepthMeshRenderer(recon, ctx)
    try:
        for t in (0.0, 0.5, 1.0):
            out = renderer.render(t, translated(), K[None], H, W)
            bright = out.colors[0, ..., 0].numpy()
            v, u = np.unravel_index(np.argmax(bright), bright.shape)
            assert (v, u) == (12, 10 + round(2 * t))
    finally:
        renderer.release()


def test_layer_weights_are_the_cameras_blend_read_when_rendering(ctx, monkeypatch):
    recon = make_recon(np.full((H, W), 5.0), texture(), depth1=np.full((H, W), 5.0))
    renderer = DepthMeshRenderer(recon, ctx)
    try:
        yaw = np.radians(40.0)
        turned = np.eye(4)
        turned[:3, :3] = np.array([[np.cos(yaw), 0, -np.sin(yaw)], [0, 1, 0], [np.sin(yaw), 0, np.cos(yaw)]])
        views = np.stack([np.eye(4), turned])
        weights = renderer.layer_weights(0.25, views)
        # both views stand at the centre of the camera of each keyframe (LayerBlend.pose_scale)
        distance = [float(np.linalg.norm(render_scene.source_centres(recon)[k].numpy(), axis=-1).min()) for k in (0, 1)]
        view_weight = [render_scene.LayerBlend().view_weight(np.cos(yaw), k, 0.25, distance[k]) for k in (0, 1)]
        expected = np.array([[1.0, view_weight[0]], [1.0, view_weight[1]]])
        np.testing.assert_allclose(weights, expected, rtol=1e-5)
        sharp = render_scene.LayerBlend(angle_scale=0.1, angle_scale_at_keyframe=0.1)  # another rule: the baseline follows
        assert renderer.layer_weights(0.25, views, sharp)[0, 1] == pytest.approx(np.exp((np.cos(yaw) - 1) / 0.1), rel=1e-5)
        # both keyframes see the same plane: the blend of two identical layers is the texture again
        out = renderer.render(0.25, views[:1], K[None], H, W)
        np.testing.assert_allclose(
            out.colors[0].numpy(), recon.images[0, 0] / 255.0, atol=1e-4
        )  # float32 interpolation; a level is 4e-3
    finally:
        renderer.release()


def test_each_image_is_back_projected_from_its_capture_pose(ctx):
    """Real rigs trigger cameras at slightly different poses: the mesh of an image taken 10 cm to the
    right renders its texture exactly from there, and not from the keyframe's pose."""
    image = texture(2)
    recon = make_recon(np.full((H, W), 5.0), image)
    capture = np.stack([np.eye(4), np.eye(4)])[:, None].copy()  # [2, V, 4, 4]
    capture[0, 0, 0, 3] = 0.1
    out = DepthMeshRenderer(recon, ctx, capture_ego_to_world=capture).render(0.0, translated(dx=0.1), K[None], H, W)
    np.testing.assert_allclose(out.colors[0].numpy(), image / 255.0, atol=1e-4)
    keyframe = DepthMeshRenderer(recon, ctx).render(0.0, translated(dx=0.1), K[None], H, W)
    assert np.abs(keyframe.colors[0].numpy() - image / 255.0).mean() > 0.05
